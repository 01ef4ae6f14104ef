// The adaptive level choice: each source's streams form a ladder (the manifest's `ladders`, from
// the fewest Mbps up); the page measures the throughput of its chunk fetches and the time it takes
// to decode a frame, picks the highest level both can keep up with, and switches only where the
// new stream has a key frame (docs/web-player.md "Adaptive levels").

// The ladders of a manifest; a site written before they were listed gets them from its streams'
// names ("nvol-high": the ladder "nvol").
export function laddersOf(manifest) {
  const index = (name) => manifest.streams.findIndex((s) => s.name === name);
  let ladders = manifest.ladders;
  if (!Array.isArray(ladders)) {
    ladders = [];
    for (const s of manifest.streams) {
      const source = s.quality && s.name.endsWith(`-${s.quality}`)
          ? s.name.slice(0, -s.quality.length - 1) : s.name;
      let ladder = ladders.find((l) => l.name === source);
      if (!ladder) ladders.push(ladder = { name: source, kind: s.kind, levels: [] });
      ladder.levels.push({ stream: s.name, quality: s.quality, mbps: s.mbps });
    }
    for (const l of ladders) l.levels.sort((a, b) => a.mbps - b.mbps);
  }
  return ladders.map((l) => ({
    name: l.name, kind: l.kind,
    levels: l.levels.map((level) => ({ ...level, index: index(level.stream) }))
                    .filter((level) => level.index >= 0),
  })).filter((l) => l.levels.length > 0);
}

// Whether frame `i` of a stream can be decoded without the frame before it: every chunk of a
// mesh or volume stream, a splat stream's key frames.
export function isKeyFrame(stream, i) {
  const chunk = stream.chunks[i];
  return stream.kind !== 'splats' || !chunk || chunk.key === true;
}

// The throughput of the chunk fetches: bytes over the time at least one response body was
// arriving (the fetches ahead share the connection, so one fetch's own rate would undercount it;
// the round trip before a body is left out: it would make small chunks read slow), smoothed over
// chunks by two moving averages, a fast one and a slow one, each of bytes over busy time (a
// sample weighs as much as the time it spans: fetches that end moments apart make a short
// sample whose rate says little). Fetches in flight together are timed once: their bytes over
// the union of their intervals, not each one's bytes over its own interval, summed (which
// counts the shared time once per fetch). While fetches are in flight it also
// watches the bytes arriving: a link that slows down shows before the chunks on it end.
export class ThroughputMeter {
  constructor() {
    this.active = 0;
    this.busySince = 0;
    this.busyMs = 0;      // time with a fetch in flight, up to the last time none was
    this.sampledMs = 0;   // busy time and bytes up to the last sample
    this.bytes = 0;
    this.sampledBytes = 0;
    this.periodBytes = 0;  // bytes since the link last went busy
    this.fast = new MovingAverage(2);  // half-lives in samples (about chunks)
    this.slow = new MovingAverage(6);
    this.samples = 0;
    this.rttMs = null;     // the shortest time to a response's first byte seen
  }

  started(now) {
    if (this.active++ === 0) {
      this.busySince = now;
      this.periodBytes = 0;
    }
  }

  // A response's headers arrived, `ms` after its request.
  responded(ms) { this.rttMs = this.rttMs === null ? ms : Math.min(this.rttMs, ms); }

  progress(bytes) {
    this.bytes += bytes;
    this.periodBytes += bytes;
  }

  ended(now) {
    if (--this.active === 0) this.busyMs += now - this.busySince;
    const busy = this.busyMs + (this.active > 0 ? now - this.busySince : 0);
    const ms = busy - this.sampledMs;
    if (ms < 1) return;  // fetches that ended together: one sample with the next
    const mbps = (this.bytes - this.sampledBytes) * 8 / 1e3 / ms;
    this.sampledMs = busy;
    this.sampledBytes = this.bytes;
    this.fast.add(mbps, ms);
    this.slow.add(mbps, ms);
    ++this.samples;
  }

  // Mbps, or null before the first sample: the smaller moving average, or less when bodies have
  // been arriving for longer than `minMs` (and 4 round trips) and brought fewer bytes over that
  // time.
  estimate(now = performance.now(), minMs = Infinity) {
    if (this.samples === 0) return null;
    let mbps = Math.min(this.fast.value, this.slow.value);
    const busyMs = now - this.busySince;
    if (this.active > 0 && busyMs >= Math.max(minMs, 4 * (this.rttMs ?? 0)))
      mbps = Math.min(mbps, this.periodBytes * 8 / 1e3 / busyMs);
    return mbps;
  }
}

// An exponential moving average of values each of a weight, decayed per sample: the weighted
// mean of the recent ones.
class MovingAverage {
  constructor(halfLife) {
    this.alpha = 0.5 ** (1 / halfLife);
    this.sum = 0;
    this.weight = 0;
  }
  add(value, weight = 1) {
    this.sum = this.alpha * this.sum + (1 - this.alpha) * value * weight;
    this.weight = this.alpha * this.weight + (1 - this.alpha) * weight;
  }
  get value() { return this.sum / this.weight; }  // without the bias towards 0 of the start
}

// What the page may spend: a level is kept while its rate is within `keep` of the measured
// throughput, and chosen on the way up only within `climb`; its decode time per frame must stay
// within `decode` of the time a frame is shown.
export const MARGINS = { keep: 0.9, climb: 0.7, decode: 0.8 };

// The level (an index into ladder.levels) the page can keep up with, from `current`: the rate a
// level needs is its Mbps times the playback speed. `decodeMs[i]` is level i's measured decode
// time per frame (undefined when not measured: scaled from the current level's by rate).
export function chooseLevel(ladder, current, throughputMbps, decodeMs, speed, fps) {
  if (throughputMbps === null) return current;
  const frameMs = 1000 / (fps * Math.max(speed, 1e-3));
  const known = decodeMs[current];
  const decodeOf = (i) => decodeMs[i] ?? (known === undefined ? 0
      : known * ladder.levels[i].mbps / Math.max(ladder.levels[current].mbps, 1e-9));
  const fits = (i, margin) => ladder.levels[i].mbps * speed <= margin * throughputMbps &&
                              decodeOf(i) <= MARGINS.decode * frameMs;
  let best = 0;
  for (let i = 0; i < ladder.levels.length; ++i)
    if (fits(i, i <= current ? MARGINS.keep : MARGINS.climb)) best = i;
  return best;
}
