// The holocap stream format, version 4 (README "The stream format"): the manifest and the
// per-frame chunks, fetched ahead of the play head and decoded in the page. Version 2 and 3
// sites are read too, but for version-3 splat chunks (another coding of the Gaussians), which
// are refused by name.

export const FORMAT_VERSION = 4;
const SPLAT_FORMAT_VERSION = 4;
export const OLDEST_FORMAT_VERSION = 2;
const readable = (version) => version >= OLDEST_FORMAT_VERSION && version <= FORMAT_VERSION;
const versions = `versions ${OLDEST_FORMAT_VERSION} to ${FORMAT_VERSION}`;
const MAGIC = 'HOLOCAPC';

export class FormatError extends Error {}

export async function loadManifest(base) {
  const response = await fetch(new URL('manifest.json', base));
  if (!response.ok) throw new FormatError(`manifest.json: HTTP ${response.status}`);
  const manifest = await response.json();
  if (manifest.format !== 'holocap-stream')
    throw new FormatError('manifest.json is not a holocap stream');
  if (!readable(manifest.version))
    throw new FormatError(`this site is stream format version ${manifest.version}; ` +
                          `this player reads ${versions}`);
  return manifest;
}

async function inflate(bytes) {
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream('deflate'));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

// Splits a chunk into its header and section views; throws FormatError when it is cut short.
export function parseChunk(buffer) {
  const bytes = new Uint8Array(buffer);
  if (bytes.length < 16 || new TextDecoder().decode(bytes.subarray(0, 8)) !== MAGIC)
    throw new FormatError('not a holocap chunk');
  const view = new DataView(buffer);
  const version = view.getUint32(8, true), headerBytes = view.getUint32(12, true);
  if (!readable(version))
    throw new FormatError(`chunk format version ${version} (this player reads ${versions})`);
  if (16 + headerBytes > bytes.length)
    throw new FormatError(`chunk truncated: ${bytes.length} bytes, header needs ${16 + headerBytes}`);
  const header = JSON.parse(new TextDecoder().decode(bytes.subarray(16, 16 + headerBytes)));
  const payload = bytes.subarray(16 + headerBytes);
  const sections = {};
  for (const s of header.sections) {
    if (s.offset + s.bytes > payload.length)
      throw new FormatError(`chunk truncated: section '${s.name}' needs ${s.offset + s.bytes} ` +
                            `bytes, ${payload.length} arrived`);
    sections[s.name] = { ...s, data: payload.subarray(s.offset, s.offset + s.bytes) };
  }
  return { header, sections, version };
}

async function sectionBytes(chunk, name) {
  const s = chunk.sections[name];
  if (!s) throw new FormatError(`chunk has no section '${name}'`);
  if (s.codec !== 'deflate') return s.data;
  const raw = await inflate(s.data);
  if (raw.length !== s.raw_bytes)
    throw new FormatError(`section '${name}' inflates to ${raw.length} bytes, not ${s.raw_bytes}`);
  return raw;
}

function typed(bytes, Type) {
  const copy = new Uint8Array(bytes);  // aligned
  return new Type(copy.buffer, 0, copy.length / Type.BYTES_PER_ELEMENT);
}

function dequantise(code, lo, hi, bits) { return lo + (hi - lo) * (code / (2 ** bits - 1)); }

// Undoes the encoder's differences: u16 elements modulo 2^16 against the one `stride` before,
// indices as zigzagged differences from the previous one.
function undoDeltas(codes, stride) {
  for (let i = stride; i < codes.length; ++i) codes[i] = (codes[i] + codes[i - stride]) & 0xffff;
  return codes;
}
function undoZigzag(codes) {
  let previous = 0;
  for (let i = 0; i < codes.length; ++i) {
    const c = codes[i];
    previous += c % 2 === 0 ? c / 2 : -(c + 1) / 2;
    codes[i] = previous;
  }
  return codes;
}

// Values stored as byte planes (every element's lowest byte, then every next byte, ...).
function fromBytePlanes(bytes, count, width, what) {
  if (bytes.length !== count * width)
    throw new FormatError(`section '${what}' holds ${bytes.length} bytes, not ${count * width}`);
  const values = new Uint32Array(count);
  for (let b = 0; b < width; ++b)
    for (let i = 0; i < count; ++i) values[i] += bytes[b * count + i] * 2 ** (8 * b);
  return values;
}

// Simplified meshes: positions as zigzagged u16 differences from the previous vertex's, indices
// as how far below the next new vertex each one lies.
function decodeCellGeometry(h, positionBytes, indexBytes) {
  const vertices = h.vertex_count, faces = h.face_count;
  const differences = fromBytePlanes(positionBytes, 3 * vertices, 2, 'positions');
  const unique = new Float32Array(3 * vertices);
  const codes = new Uint16Array(3 * vertices);
  for (let i = 0; i < 3 * vertices; ++i) {
    const c = differences[i];
    const d = c % 2 === 0 ? c / 2 : -(c + 1) / 2;
    codes[i] = ((i >= 3 ? codes[i - 3] : 0) + d) & 0xffff;
    unique[i] = dequantise(codes[i], h.box_min[i % 3], h.box_max[i % 3], h.position_bits);
  }
  const indices = fromBytePlanes(indexBytes, 3 * faces, h.index_bytes, 'indices');
  let next = 0;
  for (let i = 0; i < indices.length; ++i) {
    const code = indices[i];
    if (code > next) throw new FormatError(`index code ${code} names a vertex before the first`);
    indices[i] = next - code;
    if (code === 0) ++next;
  }
  return { unique, indices };
}

// Texture coordinates of the cell layout: face f in cell f/2 (row by row), its lower (even f)
// or upper (odd f) half, inset half a texel (and one more along the shared diagonal).
function cellUvs(layout, faces) {
  const s = layout.cell_px, width = layout.columns * s, height = layout.rows * s;
  const halves = [[[0.5, 0.5], [s - 1.5, 0.5], [0.5, s - 1.5]],
                  [[s - 0.5, s - 0.5], [1.5, s - 0.5], [s - 0.5, 1.5]]];
  const uvs = new Float32Array(6 * faces);
  for (let f = 0; f < faces; ++f) {
    const cell = Math.floor(f / 2);
    const x = (cell % layout.columns) * s, y = Math.floor(cell / layout.columns) * s;
    for (let k = 0; k < 3; ++k) {
      const [u, v] = halves[f % 2][k];
      uvs[6 * f + 2 * k] = (x + u) / width;
      uvs[6 * f + 2 * k + 1] = (y + v) / height;
    }
  }
  return uvs;
}

// A mesh chunk -> per-corner positions (and uvs + an ImageBitmap atlas, or colours).
export async function decodeMesh(chunk) {
  const h = chunk.header;
  const faces = h.face_count, vertices = h.vertex_count;
  const positionBytes = await sectionBytes(chunk, 'positions');
  let unique, indices;
  if (h.layout) {
    ({ unique, indices } = decodeCellGeometry(h, positionBytes,
                                              await sectionBytes(chunk, 'indices')));
  } else {
    unique = new Float32Array(3 * vertices);
    if (h.position_bits > 0) {
      const codes = undoDeltas(typed(positionBytes, Uint16Array), 3);
      for (let i = 0; i < 3 * vertices; ++i)
        unique[i] = dequantise(codes[i], h.box_min[i % 3], h.box_max[i % 3], h.position_bits);
    } else {
      unique.set(typed(positionBytes, Float32Array));
    }
    indices = undoZigzag(typed(await sectionBytes(chunk, 'indices'), Uint32Array));
  }
  const positions = new Float32Array(9 * faces);
  for (let c = 0; c < 3 * faces; ++c) {
    const v = indices[c];
    if (v >= vertices) throw new FormatError(`index ${v} names a missing vertex`);
    positions.set(unique.subarray(3 * v, 3 * v + 3), 3 * c);
  }
  const mesh = { kind: 'mesh', faces, positions };
  if (h.layout) {
    mesh.uvs = cellUvs(h.layout, faces);
  } else if (h.texture) {
    const uvBytes = await sectionBytes(chunk, 'uvs');
    if (h.uv_bits > 0) {
      const codes = undoDeltas(typed(uvBytes, Uint16Array), 2);
      mesh.uvs = new Float32Array(codes.length);
      for (let i = 0; i < codes.length; ++i) mesh.uvs[i] = dequantise(codes[i], 0, 1, h.uv_bits);
    } else {
      mesh.uvs = typed(uvBytes, Float32Array);
    }
  }
  if (h.texture) {
    const type = { webp: 'image/webp', jpeg: 'image/jpeg', png: 'image/png' }[h.texture.codec];
    mesh.atlas = await createImageBitmap(new Blob([chunk.sections.texture.data], { type }), {
      colorSpaceConversion: 'none', premultiplyAlpha: 'none', imageOrientation: 'none' });
  } else {
    mesh.colors = await sectionBytes(chunk, 'colors');
  }
  return mesh;
}

// A volume chunk -> the dense grid (RGBA float32, x fastest, channels as stored: B, G, R,
// density) and the occupancy cells.
export async function decodeVolume(chunk) {
  const h = chunk.header;
  const n = h.grid, brick = h.brick, cells = Math.max(h.occupancy_cells, 1);
  const occupancy = h.occupancy_cells > 0 ? await sectionBytes(chunk, 'occupancy')
                                          : new Uint8Array([1]);
  const bricks = undoZigzag(typed(await sectionBytes(chunk, 'bricks'), Uint32Array));
  const voxels = await sectionBytes(chunk, 'voxels');
  const rgba = new Float32Array(4 * n * n * n);
  const perPlane = bricks.length * brick * brick * brick;
  const floats = h.voxel === 'float32' ? typed(voxels, Float32Array) : null;
  if ((floats ? floats.length : voxels.length) !== 4 * perPlane)
    throw new FormatError(`volume voxels: ${voxels.length} bytes for ${bricks.length} bricks`);
  if (!floats) {
    // Codes stored as differences (mod 256) from the previous one in their brick row.
    for (let i = 0; i < voxels.length; ++i)
      if (i % brick !== 0) voxels[i] = (voxels[i] + voxels[i - 1]) & 0xff;
  }
  const colourLevels = 2 ** h.color_bits - 1;
  const d = h.density;
  const density = new Float32Array(256);
  for (let c = 1; c < 256; ++c)
    density[c] = d.min * Math.pow(d.max / d.min, (c - 1) / (d.levels - 2));
  let k = 0;
  for (let channel = 0; channel < 4; ++channel) {
    for (const b of bricks) {
      const bx = b % cells, by = Math.floor(b / cells) % cells, bz = Math.floor(b / (cells * cells));
      for (let z = 0; z < brick; ++z)
        for (let y = 0; y < brick; ++y) {
          let i = ((bz * brick + z) * n + by * brick + y) * n + bx * brick;
          for (let x = 0; x < brick; ++x, ++i, ++k) {
            let value;
            if (floats) value = floats[k];
            else value = channel < 3 ? voxels[k] / colourLevels : density[voxels[k]];
            rgba[4 * i + channel] = value;
          }
        }
    }
  }
  return { kind: 'volume', header: h, rgba, occupancy };
}

// Records of `width` bytes stored as byte planes (byte 0 of every record, then byte 1, ...).
function fromPlanes(planes, width, count, what) {
  if (planes.length !== width * count)
    throw new FormatError(`section '${what}' holds ${planes.length} bytes, not ${width * count}`);
  const records = new Uint8Array(planes.length);
  for (let b = 0; b < width; ++b)
    for (let i = 0, j = b; i < count; ++i, j += width) records[j] = planes[b * count + i];
  return records;
}

const SPLAT_GROUPS = ['position', 'rotation', 'scale', 'opacity', 'color'];

function splatRecordBytes(e) {
  const k = (e.sh_degree + 1) ** 2;
  return e.values === 'float32' ? [12, 16, 12, 4, 12 * k] : [6, 4, 3, 1, 3 * k];
}

// The Gaussians the codes stand for, activated as the kernels use them: unit quaternions
// (w, x, y, z), scales (metres), opacities, spherical-harmonic coefficients ((i K + k) 3 + c, BGR).
function splatsFromCodes(records, e, count) {
  const k = (e.sh_degree + 1) ** 2;
  const g = { count, degree: e.sh_degree, position: new Float32Array(3 * count),
              rotation: new Float32Array(4 * count), scale: new Float32Array(3 * count),
              opacity: new Float32Array(count), sh: new Float32Array(3 * k * count) };
  if (e.values === 'float32') {
    const f = SPLAT_GROUPS.map((_, i) => typed(records[i], Float32Array));
    g.position.set(f[0]);
    g.rotation.set(f[1]);
    g.sh.set(f[4]);
    for (let i = 0; i < 3 * count; ++i) g.scale[i] = Math.exp(f[2][i]);
    for (let i = 0; i < count; ++i) g.opacity[i] = 1 / (1 + Math.exp(-f[3][i]));
  } else {
    const [position, rotation, scale, opacity, color] = records;
    const rotationView = new DataView(rotation.buffer, rotation.byteOffset, rotation.byteLength);
    const s = Math.SQRT1_2, mask = (1 << e.rotation_bits) - 1;
    const opacityLevels = 2 ** e.opacity_bits - 1;
    for (let i = 0; i < count; ++i) {
      for (let a = 0; a < 3; ++a) {
        g.position[3 * i + a] = dequantise(position[6 * i + 2 * a] | (position[6 * i + 2 * a + 1] << 8),
                                           e.box_min[a], e.box_max[a], e.position_bits);
        g.scale[3 * i + a] = Math.exp(dequantise(scale[3 * i + a], e.log_scale_min, e.log_scale_max,
                                                 e.scale_bits));
      }
      const code = rotationView.getUint32(4 * i, true), largest = code >>> 30;
      let sum = 0, shift = 2 * e.rotation_bits;
      for (let c = 0; c < 4; ++c) {
        if (c === largest) continue;
        const v = Math.fround(dequantise((code >>> shift) & mask, -s, s, e.rotation_bits));
        g.rotation[4 * i + c] = v;
        sum += v * v;
        shift -= e.rotation_bits;
      }
      g.rotation[4 * i + largest] = Math.sqrt(Math.max(0, 1 - sum));
      g.opacity[i] = Math.min(Math.max(opacity[i] / opacityLevels, 0.5 / opacityLevels),
                              1 - 0.5 / opacityLevels);
      for (let j = 0; j < 3 * k; ++j) {
        const c = color[3 * k * i + j];
        g.sh[3 * k * i + j] = j < 3 ? dequantise(c, e.dc_min, e.dc_max, e.dc_bits)
                                    : dequantise(c, -e.rest_max, e.rest_max, e.rest_bits);
      }
    }
  }
  for (let i = 0; i < count; ++i) {  // the kernels normalise every quaternion
    const q = g.rotation.subarray(4 * i, 4 * i + 4);
    const n = Math.hypot(q[0], q[1], q[2], q[3]);
    if (n > 0) for (let c = 0; c < 4; ++c) q[c] /= n;
    else q.set([1, 0, 0, 0]);
  }
  return g;
}

// Zigzagged 16-bit numbers back to signed ones.
const unzigzag = (z) => (z & 1 ? -((z + 1) >> 1) : z >> 1);

// Position records (three 16-bit codes) stored as each code's zigzagged difference (mod 2^16)
// from the record before's, from byte `from` on, back to codes.
function unchained(chained, from) {
  const count = (chained.length - from) / 6, out = new Uint8Array(6 * count), before = [0, 0, 0];
  for (let i = 0, at = from; i < count; ++i, at += 6) {
    for (let a = 0; a < 3; ++a) {
      const z = chained[at + 2 * a] | (chained[at + 2 * a + 1] << 8);
      before[a] = (before[a] + unzigzag(z)) & 0xffff;
      out[6 * i + 2 * a] = before[a] & 0xff;
      out[6 * i + 2 * a + 1] = before[a] >> 8;
    }
  }
  return out;
}

// The motion cell of position record i: its codes over 2^bits (as one number below 2^48).
function cellOf(position, i, bits) {
  const code = (a) => position[6 * i + 2 * a] | (position[6 * i + 2 * a + 1] << 8);
  return (code(0) >> bits) * 4294967296 + (code(1) >> bits) * 65536 + (code(2) >> bits);
}

// A splat chunk -> its codes (what the next frame's delta refers to), expand() giving its
// Gaussians. A delta needs the frame before as decoded.
export async function decodeSplats(chunk, previous) {
  if (chunk.version !== undefined && chunk.version < SPLAT_FORMAT_VERSION)
    throw new FormatError(`a splat chunk of stream format version ${chunk.version}; this player ` +
                          `reads splat streams of version ${SPLAT_FORMAT_VERSION} (export the ` +
                          'site again)');
  const h = chunk.header, e = h.encoding, count = h.count, quantised = e.values !== 'float32';
  const widths = splatRecordBytes(e);
  const records = [];
  if (h.key) {
    for (const [g, name] of SPLAT_GROUPS.entries())
      records.push(fromPlanes(await sectionBytes(chunk, name), widths[g], count, name));
    if (quantised) records[0] = unchained(records[0], 0);
  } else {
    const n = h.previous;
    if (!previous || previous.count !== n)
      throw new FormatError(`a splat delta of a frame of ${n} Gaussians has no frame before it`);
    const B = Math.ceil(n / 8), masks = await sectionBytes(chunk, 'masks');
    if (masks.length !== 6 * B) throw new FormatError('splat delta masks cut short');
    const bit = (offset, i) => (masks[offset + (i >> 3)] >> (i & 7)) & 1;
    let survivors = 0;
    for (let i = 0; i < n; ++i) survivors += bit(0, i);
    if (h.added < 0 || survivors + h.added !== count)
      throw new FormatError('splat delta: survivors and added Gaussians do not make its count');
    // Quantised: each cell's mean motion (cells of the frame before's survivors, in key order).
    const motion = new Map();
    if (quantised) {
      const keys = [];
      for (let i = 0; i < n; ++i) if (bit(0, i)) keys.push(cellOf(previous.records[0], i, e.motion_cell_bits));
      keys.sort((x, y) => x - y);
      const cells = keys.filter((key, k) => k === 0 || key !== keys[k - 1]);
      if (cells.length !== h.cells)
        throw new FormatError(`splat delta: ${h.cells} motion cells where the survivors fill ${cells.length}`);
      const bytes = fromPlanes(await sectionBytes(chunk, 'motion'), 6, cells.length, 'motion');
      cells.forEach((key, c) => motion.set(key, [0, 1, 2].map(
        (a) => unzigzag(bytes[6 * c + 2 * a] | (bytes[6 * c + 2 * a + 1] << 8)))));
    }
    const top = 2 ** e.position_bits - 1;
    for (const [g, name] of SPLAT_GROUPS.entries()) {
      const w = widths[g], offset = (1 + g) * B, before = previous.records[g];
      const moving = g === 0 && quantised;
      let changed = 0;
      for (let i = 0; i < n; ++i) changed += bit(0, i) & (moving ? 1 : bit(offset, i));
      const stored = fromPlanes(await sectionBytes(chunk, name), w, changed + h.added, name);
      const out = new Uint8Array(w * count);
      let next = 0, o = 0;
      for (let i = 0; i < n; ++i) {
        if (!bit(0, i)) continue;
        if (moving) {  // the code before + its cell's motion + the residual in motion steps
          const m = motion.get(cellOf(before, i, e.motion_cell_bits));
          for (let a = 0; a < 3; ++a) {
            const r = unzigzag(stored[w * next + 2 * a] | (stored[w * next + 2 * a + 1] << 8));
            const code = Math.min(top, Math.max(0, (before[w * i + 2 * a] | (before[w * i + 2 * a + 1] << 8)) +
                                                       m[a] + r * e.motion_step));
            out[o + 2 * a] = code & 0xff;
            out[o + 2 * a + 1] = code >> 8;
          }
          ++next;
        } else if (bit(offset, i)) {  // each byte stored as its difference (mod 256) from the one before
          for (let b = 0; b < w; ++b) out[o + b] = (stored[w * next + b] + before[w * i + b]) & 0xff;
          ++next;
        } else {
          for (let b = 0; b < w; ++b) out[o + b] = before[w * i + b];
        }
        o += w;
      }
      out.set(moving ? unchained(stored, w * next) : stored.subarray(w * next), o);
      records.push(out);
    }
  }
  // The Gaussians in floats (about 240 bytes each at degree 3) are made when the frame is drawn,
  // so that the frames buffered ahead hold their codes only.
  return { kind: 'splats', header: h, count, records, gaussians: null,
           expand() { return this.gaussians ??= splatsFromCodes(records, e, count); } };
}

// Any chunk (a splat delta with the frame before's decoded data).
export function decodeChunk(parsed, previous) {
  const kind = parsed.header.kind;
  if (kind === 'mesh') return decodeMesh(parsed);
  if (kind === 'volume') return decodeVolume(parsed);
  if (kind === 'splats') return decodeSplats(parsed, previous);
  throw new FormatError(`unknown chunk kind '${kind}'`);
}

// Fetches and decodes chunks of one stream ahead of the play head; remembers failures so that a
// broken chunk is reported once and skipped.
export class StreamBuffer {
  // `onBytes(bytes, decodeMs)` after each frame decoded; `meter` (a ThroughputMeter, or null)
  // is told when each fetch starts and ends.
  constructor(base, stream, onError, onBytes, meter = null) {
    this.base = base;
    this.stream = stream;
    this.onError = onError;
    this.onBytes = onBytes;
    this.meter = meter;
    this.frames = new Map();  // index -> {state: 'loading'|'ready'|'failed', data, error}
    this.capacity = 24;  // frames kept decoded
  }

  get(index) { return this.frames.get(index); }

  // Frame `index` decoded (requested when it is not here yet); rejects when it cannot be.
  decoded(index) {
    if (index < 0 || !this.stream.chunks[index])
      return Promise.reject(new FormatError(`frame ${index} holds no data`));
    this.request(index);
    return this.frames.get(index).promise;
  }

  request(index) {
    if (index < 0 || index >= this.stream.chunks.length || this.frames.has(index)) return;
    const entry = { state: 'loading', abort: new AbortController() };
    this.frames.set(index, entry);
    const chunk = this.stream.chunks[index];
    if (!chunk) {
      entry.state = 'empty';
      return;
    }
    const url = new URL(`${this.stream.path}/${chunk.file}`, this.base);
    // A splat delta decodes from the frame before as decoded (fetched too when it is not here).
    const before = this.stream.kind === 'splats' && !chunk.key ? this.decoded(index - 1) : null;
    entry.promise = (async () => {
      // The meter times the bodies: a small chunk's request time is mostly the round trip.
      const requested = performance.now();
      const response = await fetch(url, { signal: entry.abort.signal });
      if (!response.ok) throw new FormatError(`HTTP ${response.status}`);
      const responded = performance.now();
      this.meter?.responded(responded - requested);
      this.meter?.started(responded);
      let buffer = null;
      try {
        buffer = await this.body(response);
      } finally {
        this.meter?.ended(performance.now());
      }
      if (buffer.byteLength !== chunk.bytes)
        throw new FormatError(`chunk truncated: ${buffer.byteLength} of ${chunk.bytes} bytes`);
      const parsed = parseChunk(buffer);
      let previous = null;
      if (before) {
        try {
          previous = await before;
        } catch (error) {
          throw new FormatError(`the frame before did not decode (${error.message})`);
        }
      }
      const decodeStart = performance.now();
      const data = await decodeChunk(parsed, previous);
      this.onBytes(buffer.byteLength, performance.now() - decodeStart);
      return data;
    })();
    entry.promise.catch(() => {});  // reported below, once
    entry.promise.then((data) => {
      entry.state = 'ready';
      entry.data = data;
    }, (error) => {
      if (entry.abort.signal.aborted) return;  // dropped on purpose (cancel)
      entry.state = 'failed';
      entry.error = error;
      this.onError(index, `${this.stream.name} frame ${index} (${chunk.file}): ${error.message}`);
    });
  }

  // A response's body, its bytes told to the meter as they arrive.
  async body(response) {
    if (!this.meter || !response.body) return response.arrayBuffer();
    const reader = response.body.getReader(), parts = [];
    let length = 0;
    for (;;) {
      const { done, value } = await reader.read();
      if (done) break;
      parts.push(value);
      length += value.length;
      this.meter.progress(value.length);
    }
    const bytes = new Uint8Array(length);
    let offset = 0;
    for (const part of parts) {
      bytes.set(part, offset);
      offset += part.length;
    }
    return bytes.buffer;
  }

  // Stops the fetches in flight of frames outside `wanted` (a set of indices) and forgets them;
  // not in a splat stream, where such a frame may be the one a wanted delta decodes from.
  cancel(wanted) {
    if (this.stream.kind === 'splats') return;
    for (const [i, entry] of this.frames) {
      if (entry.state !== 'loading' || wanted.has(i)) continue;
      entry.abort.abort();
      this.frames.delete(i);
    }
  }

  // Keeps the frames from `index` on (wrapping when looping) and drops the rest.
  // Returns the indices wanted.
  prefetch(index, ahead, loop) {
    const count = this.stream.chunks.length;
    const wanted = new Set();
    for (let k = 0; k < Math.min(ahead, count); ++k) {
      let i = index + k;
      if (i >= count) {
        if (!loop) break;
        i %= count;
      }
      wanted.add(i);
      this.request(i);
    }
    if (this.frames.size > this.capacity) {
      for (const [i, entry] of this.frames)
        if (!wanted.has(i) && entry.state !== 'loading' && entry.state !== 'failed')
          this.frames.delete(i);
    }
    return wanted;
  }

  // Frames ready from `index` on, before the first that is not.
  readyAhead(index) {
    let n = 0;
    for (let i = index; i < this.stream.chunks.length; ++i) {
      const e = this.frames.get(i);
      if (!e || (e.state !== 'ready' && e.state !== 'failed' && e.state !== 'empty')) break;
      ++n;
    }
    return n;
  }
}
