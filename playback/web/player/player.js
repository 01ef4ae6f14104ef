// The holocap player: plays a site written by `holocap export web` (manifest.json + chunks).
// The URL's hash is the permalink: frame=K, stream=NAME, and either camera=N (look through
// capture camera N) or eye=x,y,z&target=x,y,z&fov=DEG; play=1, speed=S, loop=0, helpers=0,
// background=0 (the subject alone over black where the stream has a background behind it when
// looking through a capture camera) and ui=0 (no overlays) are optional. A stream named alone
// is pinned; level=auto lets the page move along its ladder (a ladder's name, e.g. stream=mesh,
// or no stream at all, is adaptive too), level=QUALITY pins that level of the ladder; buffer=N
// fetches N frames ahead of the play head (8; the page keeps 3N of a stream's frames decoded).
// window.holocap exposes the state for tests and tools (window.holocap.abr: the level choice).
import { captureCamera, cameraCentre, cross, dot, lookAt, multiply, normalize, projectionMatrix,
         scale, add, sub, norm, viewMatrix } from './math.js';
import { FormatError, StreamBuffer, decodeChunk, loadManifest, parseChunk } from './stream.js';
import { ThroughputMeter, chooseLevel, isKeyFrame, laddersOf } from './ladder.js';
import { MeshRenderer } from './mesh.js';
import { VolumeRenderer } from './volume.js';
import { SplatRenderer } from './splat.js';
import { BackgroundRenderer } from './background.js';
import { LineRenderer, floorLines, frustumLines } from './helpers.js';

const $ = (id) => document.getElementById(id);
const base = new URL('.', window.location.href);

const state = {
  manifest: null, buffers: [], stream: 0, frame: 0, time: 0, playing: false, loop: true,
  speed: 1, helpers: true, background: true, drawnBackground: null, drawnFrame: -1,
  drawnStream: null, messages: [],
  fatal: null, timeToFirstFrameMs: null, decoded: [], drawTimes: [], fly: false,
  view: null,  // {mode: 'orbit', target, radius, azimuth, elevation, fov} | {mode: 'capture', index}
               // | {mode: 'fly', eye, yaw, pitch, fov}
  ladders: [], meter: new ThroughputMeter(),
  decodeMs: [],  // per stream: decode time per frame, smoothed
  ahead: 8,  // frames fetched ahead of the play head
  // The level choice: auto (or pinned), the pending switch {stream, at, down} (at: the target's
  // key frame where it happens), every switch made, and the stalls while playing (a stall: the
  // next frame due and not decoded), measured in frames at the playing speed.
  abr: { auto: true, pending: null, switches: [], stalls: 0, longestStallFrames: 0,
         stalledSince: null, framesPlayed: 0 },
};
window.holocap = state;

function message(text) {
  state.messages.push(text);
  const line = document.createElement('div');
  line.textContent = text;
  $('messages').appendChild(line);
  while ($('messages').childElementCount > 6) $('messages').firstChild.remove();
}

function fatal(text) {
  state.fatal = text;
  $('fatal').textContent = text;
}

// ---------------------------------------------------------------------------------------------
// The view

function upAxis() { return normalize(state.manifest.up); }
function boundsCentre() {
  const b = state.manifest.bounds;
  return scale(add(b.min, b.max), 0.5);
}
// Two directions spanning the floor, for azimuths.
function floorAxes() {
  const up = upAxis();
  let a = cross(up, [0, 0, 1]);
  if (norm(a) < 0.1) a = cross(up, [1, 0, 0]);
  a = normalize(a);
  return [a, cross(up, a)];
}

function orbitFromEye(eye, target, fov) {
  const up = upAxis(), [a, b] = floorAxes();
  const offset = sub(eye, target);
  const radius = norm(offset);
  return { mode: 'orbit', target, radius, fov, azimuth: Math.atan2(dot(offset, b), dot(offset, a)),
           elevation: Math.asin(Math.max(-1, Math.min(1, dot(offset, up) / radius))) };
}

function defaultView() {
  const c = state.manifest.cameras[0];
  const centre = boundsCentre();
  if (!c) return { mode: 'orbit', target: centre, radius: 3, azimuth: 0, elevation: 0.2, fov: 50 };
  const cam = captureCamera(c, c.width, c.height);
  return orbitFromEye(cameraCentre(cam), centre, 2 * Math.atan(c.width / 2 / c.pinhole[0]) * 180 / Math.PI);
}

function eyeOf(view) {
  if (view.mode === 'fly') return view.eye;
  const up = upAxis(), [a, b] = floorAxes();
  const horizontal = add(scale(a, Math.cos(view.azimuth)), scale(b, Math.sin(view.azimuth)));
  const direction = add(scale(horizontal, Math.cos(view.elevation)), scale(up, Math.sin(view.elevation)));
  return add(view.target, scale(direction, view.radius));
}

function targetOf(view) {
  if (view.mode !== 'fly') return view.target;
  const up = upAxis(), [a, b] = floorAxes();
  const horizontal = add(scale(a, Math.cos(view.yaw)), scale(b, Math.sin(view.yaw)));
  return add(view.eye, add(scale(horizontal, Math.cos(view.pitch)), scale(up, Math.sin(view.pitch))));
}

// The camera drawn this frame, on a W x H canvas.
function currentCamera(W, H) {
  const view = state.view;
  if (view.mode === 'capture') return captureCamera(state.manifest.cameras[view.index], W, H);
  const pose = lookAt(eyeOf(view), targetOf(view), upAxis());
  const f = 0.5 * W / Math.tan(0.5 * view.fov * Math.PI / 180);
  return { ...pose, fx: f, fy: f, cx: (W - 1) / 2, cy: (H - 1) / 2 };
}

// Leaves "look through camera N" for the orbit around the subject from the same place.
function toOrbit() {
  if (state.view.mode === 'orbit') return;
  const canvas = $('view');
  const cam = currentCamera(canvas.width, canvas.height);
  const fov = 2 * Math.atan(canvas.width / 2 / cam.fx) * 180 / Math.PI;
  const eye = cameraCentre(cam);
  const forward = cam.R[2];
  const target = state.view.mode === 'fly' ? targetOf(state.view)
      : add(eye, scale(forward, Math.max(0.5, dot(sub(boundsCentre(), eye), forward))));
  state.view = orbitFromEye(eye, target, fov);
}

// ---------------------------------------------------------------------------------------------
// The permalink

function writeHash() {
  const v = state.view, parts = [`frame=${state.frame}`];
  const stream = state.manifest.streams[state.stream];
  if (stream) parts.push(`stream=${encodeURIComponent(stream.name)}`);
  if (state.abr.auto) parts.push('level=auto');
  if (v.mode === 'capture') {
    parts.push(`camera=${v.index}`);
  } else {
    const f = (x) => x.map((c) => c.toFixed(4)).join(',');
    parts.push(`eye=${f(eyeOf(v))}`, `target=${f(targetOf(v))}`, `fov=${v.fov.toFixed(2)}`);
    if (v.mode === 'fly') parts.push('fly=1');
  }
  if (state.playing) parts.push('play=1');
  if (state.speed !== 1) parts.push(`speed=${state.speed}`);
  if (!state.loop) parts.push('loop=0');
  if (!state.helpers) parts.push('helpers=0');
  if (!state.background) parts.push('background=0');
  if (state.ahead !== 8) parts.push(`buffer=${state.ahead}`);
  if (document.body.classList.contains('bare')) parts.push('ui=0');
  const hash = '#' + parts.join('&');
  if (window.location.hash !== hash) history.replaceState(null, '', hash);
  $('permalink').href = hash;
}

function readHash() {
  const p = new URLSearchParams(window.location.hash.slice(1));
  const numbers = (key) => (p.get(key) || '').split(',').map(Number);
  const frames = state.manifest.frames.length;
  if (p.has('frame')) state.frame = Math.max(0, Math.min(frames - 1, parseInt(p.get('frame'), 10) || 0));
  state.time = state.frame;
  // A stream named alone is pinned, as its permalink drew it; a ladder's name starts it from its
  // lowest level, adaptively.
  let auto = !p.has('stream');
  if (p.has('stream')) {
    const index = state.manifest.streams.findIndex((s) => s.name === p.get('stream'));
    const ladder = state.ladders.find((l) => l.name === p.get('stream'));
    if (index >= 0) state.stream = index;
    else if (ladder) state.stream = ladder.levels[0].index;
    else message(`no stream '${p.get('stream')}' in this site`);
    auto = index < 0;
  }
  if (p.has('level')) {
    const level = p.get('level');
    const pinned = ladderOf(state.stream).levels.find((l) => l.quality === level);
    if (level === 'auto') auto = true;
    else if (pinned) {
      auto = false;
      state.stream = pinned.index;
    } else message(`no level '${level}' in the ladder ${ladderOf(state.stream).name}`);
  }
  if (state.buffers.length > 0) setLevelMode(state.stream, auto);
  else state.abr.auto = auto;
  const camera = parseInt(p.get('camera'), 10);
  if (p.has('camera') && camera >= 0 && camera < state.manifest.cameras.length) {
    state.view = { mode: 'capture', index: camera };
  } else if (p.has('eye') && p.has('target')) {
    const eye = numbers('eye'), target = numbers('target');
    if (eye.length === 3 && target.length === 3 && eye.concat(target).every(Number.isFinite)) {
      state.view = orbitFromEye(eye, target, Number(p.get('fov')) || 50);
      if (p.get('fly') === '1') setFly(true);
    }
  }
  state.playing = p.get('play') === '1';
  state.speed = Number(p.get('speed')) || 1;
  state.loop = p.get('loop') !== '0';
  state.helpers = p.get('helpers') !== '0';
  state.background = p.get('background') !== '0';
  state.ahead = Math.max(1, Math.min(64, parseInt(p.get('buffer'), 10) || 8));
  for (const buffer of state.buffers) buffer.capacity = 3 * state.ahead;
  document.body.classList.toggle('bare', p.get('ui') === '0');
}

// ---------------------------------------------------------------------------------------------
// Input: orbit (drag), pan (right drag or shift), zoom (wheel), fly (WASD/QE + drag to look)

function setFly(on) {
  state.fly = on;
  $('fly').textContent = on ? 'orbit' : 'fly';
  if (on) {
    const canvas = $('view');
    const cam = currentCamera(canvas.width, canvas.height);
    const eye = cameraCentre(cam), forward = cam.R[2], up = upAxis(), [a, b] = floorAxes();
    state.view = { mode: 'fly', eye, fov: 2 * Math.atan(canvas.width / 2 / cam.fx) * 180 / Math.PI,
                   yaw: Math.atan2(dot(forward, b), dot(forward, a)),
                   pitch: Math.asin(Math.max(-1, Math.min(1, dot(forward, up)))) };
  } else {
    toOrbit();
  }
}

function installInput(canvas) {
  let drag = null;
  canvas.addEventListener('pointerdown', (e) => {
    drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener('pointerup', () => { drag = null; });
  canvas.addEventListener('contextmenu', (e) => e.preventDefault());
  canvas.addEventListener('pointermove', (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX;
    drag.y = e.clientY;
    if (state.view.mode === 'capture') toOrbit();
    const v = state.view;
    if (v.mode === 'fly') {
      v.yaw -= dx * 0.005;
      v.pitch = Math.max(-1.5, Math.min(1.5, v.pitch - dy * 0.005));
    } else if (drag.pan) {
      const cam = currentCamera(canvas.width, canvas.height);
      const metresPerPixel = v.radius / cam.fx;
      v.target = add(v.target, add(scale(cam.R[0], -dx * metresPerPixel), scale(cam.R[1], -dy * metresPerPixel)));
    } else {
      v.azimuth -= dx * 0.008;
      v.elevation = Math.max(-1.5, Math.min(1.5, v.elevation + dy * 0.008));
    }
  });
  canvas.addEventListener('wheel', (e) => {
    e.preventDefault();
    if (state.view.mode === 'capture') toOrbit();
    const v = state.view, factor = Math.exp(e.deltaY * 0.001);
    if (v.mode === 'fly') v.fov = Math.max(5, Math.min(120, v.fov * factor));
    else v.radius = Math.max(0.05, v.radius * factor);
  }, { passive: false });
  const keys = new Set();
  window.addEventListener('keydown', (e) => {
    if (e.target.tagName === 'INPUT' && e.target.type !== 'range') return;
    if (e.key === ' ') { togglePlay(); e.preventDefault(); }
    else if (e.key === '.') stepFrame(1);
    else if (e.key === ',') stepFrame(-1);
    else if (e.key === 'f') setFly(!state.fly);
    keys.add(e.key.toLowerCase());
  });
  window.addEventListener('keyup', (e) => keys.delete(e.key.toLowerCase()));
  return (dt) => {
    const v = state.view;
    if (v.mode !== 'fly' || keys.size === 0) return;
    const forward = normalize(sub(targetOf(v), v.eye)), up = upAxis();
    const right = normalize(cross(forward, up)), speed = 1.0 * dt;
    const move = { w: forward, s: scale(forward, -1), d: right, a: scale(right, -1), e: up, q: scale(up, -1) };
    for (const [key, direction] of Object.entries(move))
      if (keys.has(key)) v.eye = add(v.eye, scale(direction, speed));
  };
}

// ---------------------------------------------------------------------------------------------
// Playback

function frameCount() { return state.manifest.frames.length; }

function setFrame(index) {
  const n = frameCount();
  state.frame = state.loop ? ((index % n) + n) % n : Math.max(0, Math.min(n - 1, index));
  state.time = state.frame;
}

function stepFrame(delta) {
  state.playing = false;
  state.abr.pending = null;
  setFrame(state.frame + delta);
}

function togglePlay() {
  state.playing = !state.playing;
  if (state.playing && !state.loop && state.frame === frameCount() - 1) setFrame(0);
}

// Frames from `from` to `to` in playing order (wrapping when looping).
function framesBetween(from, to) {
  const n = frameCount();
  return state.loop ? ((to - from) % n + n) % n : to - from;
}

// Stream `s`'s first key frame from frame `from` on (wrapping when looping); -1 when none.
function nextKeyFrame(s, from) {
  const stream = state.manifest.streams[s], n = frameCount();
  for (let k = 0; k < n; ++k) {
    let i = from + k;
    if (i >= n) {
      if (!state.loop) return -1;
      i %= n;
    }
    if (isKeyFrame(stream, i)) return i;
  }
  return -1;
}

function stalled(now, stalling) {
  const abr = state.abr;
  if (stalling && abr.stalledSince === null) abr.stalledSince = now;
  if (stalling || abr.stalledSince === null) return;
  abr.longestStallFrames = Math.max(abr.longestStallFrames, stallFrames(now));
  ++abr.stalls;
  abr.stalledSince = null;
  // A level that stalled (and every one above it) is not climbed to again for a while: a short
  // chunk's throughput reads high (a link's first packets come in a burst).
  if (abr.auto) abr.stalledLevel = { stream: state.stream, until: abr.framesPlayed + 4 * state.ahead };
}

function stallFrames(now) {
  const since = state.abr.stalledSince;
  return since === null ? 0 : (now - since) / 1000 * state.manifest.fps * state.speed;
}

const ready = (entry) => entry && entry.state !== 'loading';

function advance(dt, now) {
  if (!state.playing) return stalled(now, false);
  const next = state.frame + 1 < frameCount() ? state.frame + 1 : (state.loop ? 0 : -1);
  if (next < 0) {
    state.playing = false;
    return stalled(now, false);
  }
  // At a pending switch's key frame: the new stream's frame when it is here, else the old one's
  // (the switch moves to the new stream's next key frame), else whichever comes first.
  const pending = state.abr.pending;
  let stream = state.stream;
  if (pending && next === pending.at && (ready(state.buffers[pending.stream].get(next)) ||
                                         !ready(state.buffers[stream].get(next))))
    stream = pending.stream;
  const entry = state.buffers[stream].get(next);
  // Waits for a frame still on its way (buffering: a stall once it is due); a failed or empty one
  // is passed over.
  state.time += dt * state.speed * state.manifest.fps;
  if (!ready(entry)) {
    state.time = Math.min(state.time, state.frame + 1);
    if (state.time >= state.frame + 1 && state.timeToFirstFrameMs !== null) stalled(now, true);
    return;
  }
  stalled(now, false);
  if (state.time < state.frame + 1) return;
  // What is left of the tick counts towards the next frame (a frame at most: a slow page drops
  // frames rather than run behind).
  const carry = Math.min(state.time - (state.frame + 1), 0.99);
  if (pending && next === pending.at) {
    if (stream === pending.stream) switchTo(stream, next);
    else pending.at = nextKeyFrame(pending.stream, next + 1);
    if (state.abr.pending && state.abr.pending.at < 0) state.abr.pending = null;
  }
  setFrame(next);
  state.time += carry;
  ++state.abr.framesPlayed;
}

// ---------------------------------------------------------------------------------------------
// The ladder: the level chosen from the measured throughput and decode time

function ladderOf(s) {
  const name = state.manifest.streams[s].name;
  return state.ladders.find((l) => l.levels.some((level) => level.stream === name));
}
function levelOf(s) {
  return ladderOf(s).levels.findIndex((level) => level.index === s);
}

function switchTo(s, frame) {
  const abr = state.abr, streams = state.manifest.streams;
  if (s !== state.stream) {
    abr.switches.push({ frame, from: streams[state.stream].name, to: streams[s].name,
                        fromMbps: streams[state.stream].mbps, toMbps: streams[s].mbps,
                        throughputMbps: state.meter.estimate(), auto: abr.auto,
                        key: isKeyFrame(streams[s], frame) });
  }
  state.stream = s;
  abr.pending = null;
}

// Pins stream `s` (auto = false) or lets the page choose along its ladder.
function setLevelMode(s, auto) {
  state.abr.auto = auto;
  state.abr.pending = null;
  if (s !== state.stream) switchTo(s, state.frame);
  fillLevels();
}

// Plans a switch when the level the page can keep up with is not the one playing: at the new
// stream's first key frame after the frames of the old one already decoded ahead.
function chooseAdaptively() {
  const abr = state.abr;
  if (!abr.auto || !state.playing) return;
  const ladder = ladderOf(state.stream), current = levelOf(state.stream);
  const decodeMs = ladder.levels.map((level) => state.decodeMs[level.index]);
  const stalledAt = abr.stalledLevel && abr.framesPlayed < abr.stalledLevel.until
      ? ladder.levels.findIndex((level) => level.index === abr.stalledLevel.stream) : -1;
  // The link watched live over a frame's time at least: a slowing link shows before the
  // chunks on it end.
  const frameMs = 1000 / (state.manifest.fps * Math.max(state.speed, 1e-3));
  let best = chooseLevel(ladder, current, state.meter.estimate(performance.now(), frameMs),
                         decodeMs, state.speed, state.manifest.fps);
  if (stalledAt >= 0) best = Math.min(best, Math.max(0, stalledAt - 1));
  if (best === current) {
    abr.pending = null;
    return;
  }
  const target = ladder.levels[best].index;
  if (abr.pending?.stream === target) return;
  const ahead = Math.max(1, state.buffers[state.stream].readyAhead(state.frame));
  const at = nextKeyFrame(target, (state.frame + ahead) % frameCount());
  abr.pending = at < 0 ? null : { stream: target, at, down: best < current };
}

// The frames to fetch: the playing stream's ahead of the play head up to a pending switch's key
// frame (on the way down, before it: the link is left to the new stream, and the old stream's
// frames in flight beyond are dropped), the new stream's from there.
function prefetch() {
  const pending = state.abr.pending, ahead = state.ahead;
  if (!pending) return state.buffers[state.stream].prefetch(state.frame, ahead, state.loop);
  const old = state.buffers[state.stream];
  const span = Math.max(1, framesBetween(state.frame, pending.at) + (pending.down ? 0 : 1));
  old.cancel(old.prefetch(state.frame, span, state.loop));
  state.buffers[pending.stream].prefetch(pending.at, ahead, state.loop);
}

function updateStats(now) {
  const windowMs = 1000;
  state.drawTimes = state.drawTimes.filter((t) => now - t < windowMs);
  state.decoded = state.decoded.filter((d) => now - d.t < windowMs);
  const bytes = state.decoded.reduce((s, d) => s + d.bytes, 0);
  const buffer = state.buffers[state.stream];
  const ahead = buffer ? buffer.readyAhead(state.frame) : 0;
  state.stats = { fps: state.drawTimes.length, decodedMBps: bytes / 1e6, decodedFramesPerSecond: state.decoded.length,
                  bufferAheadFrames: ahead, bufferAheadS: ahead / state.manifest.fps };
  const stream = state.manifest.streams[state.stream], abr = state.abr;
  const throughput = state.meter.estimate();
  abr.stream = stream.name;
  abr.ladder = ladderOf(state.stream).name;
  abr.level = stream.quality;
  abr.mbps = stream.mbps;
  abr.throughputMbps = throughput;
  abr.decodeMs = state.decodeMs[state.stream] ?? null;
  abr.stallingFrames = stallFrames(now);
  abr.switchingTo = abr.pending ? { stream: state.manifest.streams[abr.pending.stream].name, at: abr.pending.at } : null;
  for (const [key, value] of Object.entries({ stream: stream.name, level: stream.quality,
                                              levelMode: abr.auto ? 'auto' : 'pinned',
                                              mbps: stream.mbps.toFixed(2) }))
    document.body.dataset[key] = value;
  $('stats').textContent =
      `fps        ${state.stats.fps}\n` +
      `decoded    ${state.stats.decodedMBps.toFixed(2)} MB/s (${state.decoded.length} frames/s)\n` +
      `buffer     ${ahead} frames (${state.stats.bufferAheadS.toFixed(2)} s ahead)\n` +
      `stream     ${stream.name}\n` +
      `level      ${stream.quality} ${stream.mbps.toFixed(1)} Mbps ${abr.auto ? 'auto' : 'pinned'}` +
      (abr.switchingTo ? ` -> ${abr.switchingTo.stream} at ${abr.switchingTo.at}` : '') + '\n' +
      `link       ${throughput === null ? '-' : throughput.toFixed(1) + ' Mbps measured'}` +
      (state.drawnSplats ? `\nsplats     ${state.drawnSplats.drawn} of ${state.drawnSplats.count} drawn` : '');
}

// ---------------------------------------------------------------------------------------------
// Drawing

function draw(gl, renderers) {
  const canvas = $('view');
  const W = canvas.width, H = canvas.height;
  gl.viewport(0, 0, W, H);
  gl.clearColor(0, 0, 0, 1);
  gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  const camera = currentCamera(W, H);
  const centre = boundsCentre(), distance = norm(sub(cameraCentre(camera), centre));
  const projection = projectionMatrix(camera, W, H, Math.max(0.01, distance * 0.01), distance * 10 + 20);
  const view = viewMatrix(camera);
  const stream = state.manifest.streams[state.stream];
  // Through a capture camera, what the stream's source sees behind the subject there.
  state.drawnBackground = null;
  if (state.background && state.view.mode === 'capture' && stream?.backgrounds) {
    const c = state.manifest.cameras[state.view.index];
    const url = stream.backgrounds[c.name];
    if (url) state.drawnBackground = renderers.background.draw(url, c, W, H);
  }
  if (state.helpers) {
    renderers.floor.draw(view, projection);
    renderers.frusta.draw(view, projection);
  }
  const entry = state.buffers[state.stream]?.get(state.frame);
  if (!stream || !entry) return;
  if (entry.state === 'ready') {
    if (entry.data.kind === 'mesh') renderers.mesh.draw(entry.data, view, projection);
    else if (entry.data.kind === 'splats') renderers.splats.draw(entry.data, camera, W, H);
    else renderers.volume.draw(entry.data, camera, H);
    state.drawnSplats = entry.data.kind === 'splats'
        ? { drawn: renderers.splats.drawn, count: entry.data.count } : null;
    if (state.drawnFrame !== state.frame && state.timeToFirstFrameMs === null)
      state.timeToFirstFrameMs = performance.now();
  }
  if (state.drawnBackground === 'loading') return;  // the frame is drawn once its background is
  if (entry.state === 'ready' || entry.state === 'failed' || entry.state === 'empty') {
    state.drawnFrame = state.frame;
    state.drawnStream = stream.name;
    state.drawnState = entry.state;
  }
}

function resize(canvas) {
  const ratio = window.devicePixelRatio || 1;
  const w = Math.round(canvas.clientWidth * ratio), h = Math.round(canvas.clientHeight * ratio);
  if (canvas.width !== w || canvas.height !== h) {
    canvas.width = w;
    canvas.height = h;
  }
}

// The level menu: auto, then the ladder's levels from the fewest Mbps up.
function fillLevels() {
  const menu = $('level'), ladder = ladderOf(state.stream);
  if (!menu) return;
  menu.replaceChildren(new Option(`auto (${ladder.name})`, 'auto'));
  for (const level of ladder.levels)
    menu.add(new Option(`${level.quality} (${level.mbps.toFixed(1)} Mbps)`, String(level.index)));
  menu.value = state.abr.auto ? 'auto' : String(state.stream);
  $('stream').value = String(state.stream);
}

function buildUi(renderers) {
  const m = state.manifest;
  $('timeline').max = String(frameCount() - 1);
  for (const [i, s] of m.streams.entries())
    $('stream').add(new Option(`${s.name} (${s.mbps.toFixed(1)} Mbps)`, String(i)));
  for (const [i, c] of m.cameras.entries()) $('camera').add(new Option(`${i}: ${c.name}`, String(i)));
  $('stream').value = String(state.stream);
  $('stream').onchange = () => setLevelMode(Number($('stream').value), false);
  $('level').onchange = () => {
    const value = $('level').value;
    if (value === 'auto') setLevelMode(state.stream, true);
    else setLevelMode(Number(value), false);
  };
  fillLevels();
  $('play').onclick = togglePlay;
  $('back').onclick = () => stepFrame(-1);
  $('forward').onclick = () => stepFrame(1);
  $('timeline').oninput = () => {
    state.playing = false;
    state.abr.pending = null;
    setFrame(Number($('timeline').value));
  };
  $('loop').checked = state.loop;
  $('loop').onchange = () => { state.loop = $('loop').checked; };
  $('speed').value = String(state.speed);
  $('speed').onchange = () => { state.speed = Number($('speed').value); };
  $('helpers').checked = state.helpers;
  $('helpers').onchange = () => { state.helpers = $('helpers').checked; };
  $('look').onclick = () => {
    state.view = { mode: 'capture', index: Number($('camera').value) };
    if (state.fly) { state.fly = false; $('fly').textContent = 'fly'; }
  };
  $('fly').onclick = () => setFly(!state.fly);
  renderers.floor.set(floorLines(m));
}

async function main() {
  const canvas = $('view');
  const gl = canvas.getContext('webgl2', { antialias: false, preserveDrawingBuffer: true, alpha: false });
  if (!gl) return fatal('this browser has no WebGL2');
  try {
    state.manifest = await loadManifest(base);
  } catch (error) {
    return fatal(error instanceof FormatError ? error.message : `cannot load the site: ${error.message}`);
  }
  const m = state.manifest;
  if (m.frames.length === 0 || m.streams.length === 0) return fatal('this site holds no frames');
  state.ladders = laddersOf(m);
  state.buffers = m.streams.map((s, index) => new StreamBuffer(base, s, (i, text) => message(text),
      (bytes, decodeMs) => {
        state.decoded.push({ t: performance.now(), bytes });
        const before = state.decodeMs[index];
        state.decodeMs[index] = before === undefined ? decodeMs : 0.7 * before + 0.3 * decodeMs;
      }, state.meter));
  state.view = defaultView();
  readHash();
  const renderers = { mesh: new MeshRenderer(gl), volume: new VolumeRenderer(gl), splats: new SplatRenderer(gl),
                      floor: new LineRenderer(gl), frusta: new LineRenderer(gl),
                      background: new BackgroundRenderer(gl, base) };
  buildUi(renderers);
  const moveFly = installInput(canvas);
  window.addEventListener('hashchange', () => readHash());
  let last = performance.now(), selected = null;
  const tick = (now) => {
    const dt = Math.min(0.1, (now - last) / 1000);
    last = now;
    resize(canvas);
    moveFly(dt);
    advance(dt, now);
    chooseAdaptively();
    prefetch();
    const look = state.view.mode === 'capture' ? state.view.index : -1;
    if (look !== selected) {
      renderers.frusta.set(frustumLines(m, look));
      selected = look;
    }
    draw(gl, renderers);
    state.drawTimes.push(now);
    updateStats(now);
    $('timeline').value = String(state.frame);
    $('frame-label').textContent = `${state.frame + 1} / ${frameCount()}  ${m.frames[state.frame].time_s.toFixed(2)} s`;
    $('play').textContent = state.playing ? 'pause' : 'play';
    writeHash();
    requestAnimationFrame(tick);
  };
  requestAnimationFrame(tick);
}

// Fetches and decodes every chunk of a stream in turn (nothing drawn): the page's decoding rate.
state.benchDecode = async (name) => {
  const stream = state.manifest.streams.find((s) => s.name === name);
  let frames = 0, bytes = 0, decodeMs = 0, previous = null;
  const start = performance.now();
  for (const chunk of stream.chunks) {
    if (!chunk) continue;
    const buffer = await (await fetch(new URL(`${stream.path}/${chunk.file}`, base))).arrayBuffer();
    const t = performance.now();
    const parsed = parseChunk(buffer);
    previous = await decodeChunk(parsed, previous);  // splat deltas: from the frame before
    previous.expand?.();  // a splat frame's Gaussians, as drawing it makes them
    decodeMs += performance.now() - t;
    bytes += buffer.byteLength;
    ++frames;
  }
  const seconds = (performance.now() - start) / 1000;
  return { frames, bytes, seconds, decodeSeconds: decodeMs / 1000,
           framesDecodedPerSecond: frames / (decodeMs / 1000) };
};

main();
