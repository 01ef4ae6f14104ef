// The page's level choice and throughput meter (playback/web/player/ladder.js) under node's test
// runner, on their own: `node --test tests/playback/browser/ladder_test.mjs` (ctest runs it as
// WebLadderJs).
import assert from 'node:assert/strict';
import test from 'node:test';
import { ThroughputMeter, chooseLevel } from '../../../playback/web/player/ladder.js';

// The splat ladder of bench/web_bench_results.txt (Mbps at 30 fps) with the decode times per
// frame the page measured for it (docs/benchmarks.md, "Playback in the page": SwiftShader).
const splats = { levels: [{ stream: 'splat-low', mbps: 63.06 }, { stream: 'splat-medium', mbps: 67.84 },
                          { stream: 'splat-high', mbps: 68.04 }] };
const measured = [26.4, 47.2, 189.1];

test('a level whose decode time exceeds the frame time is not chosen, whatever the link', () => {
  // 30 fps: 33.3 ms a frame, 26.7 ms of it for decoding; only splat-low decodes in time.
  for (const current of [0, 1, 2])
    assert.equal(chooseLevel(splats, current, 1000, measured, 1, 30), 0);
  // At a quarter of the speed a frame is shown for 133 ms: splat-medium decodes in time,
  // splat-high (189 ms) still does not.
  assert.equal(chooseLevel(splats, 0, 1000, measured, 0.25, 30), 1);
  assert.equal(chooseLevel(splats, 2, 1000, measured, 0.25, 30), 1);
  // Where the link holds it, the link decides: a quarter of splat-medium's rate (17.0 Mbps)
  // climbs within 0.7 of 25 Mbps, not of 20.
  assert.equal(chooseLevel(splats, 0, 20, measured, 0.25, 30), 0);
  assert.equal(chooseLevel(splats, 0, 25, measured, 0.25, 30), 1);
});

test('an unmeasured level is estimated from the current one by rate', () => {
  // Only splat-low measured (26.4 ms): splat-medium is estimated at 26.4 x 67.84 / 63.06 =
  // 28.4 ms, over the 26.7 ms a 30 fps frame leaves; at half speed it fits.
  const lowOnly = [26.4, undefined, undefined];
  assert.equal(chooseLevel(splats, 0, 1000, lowOnly, 1, 30), 0);
  assert.equal(chooseLevel(splats, 0, 1000, lowOnly, 0.5, 30), 2);
  // Nothing measured yet: the rate alone.
  assert.equal(chooseLevel(splats, 0, 1000, [], 1, 30), 2);
});

// A link of `mbps` shared evenly by the fetches on it, in steps of 1 ms: fetch k of `sizes[k]`
// bytes starts at `starts[k]` ms; the meter told as the page tells it. Returns the meter and each
// fetch's own rate (its bytes over its own interval, Mbps).
function simulate(mbps, starts, sizes) {
  const meter = new ThroughputMeter();
  const left = [...sizes], own = [];
  const perMs = mbps * 1e6 / 8 / 1e3;
  for (let t = 0, done = 0; done < sizes.length; ++t) {
    starts.forEach((s, k) => { if (s === t) meter.started(t); });
    const active = left.map((b, k) => k).filter((k) => starts[k] <= t && left[k] > 0);
    for (const k of active) {
      const bytes = Math.min(left[k], perMs / active.length);
      left[k] -= bytes;
      meter.progress(bytes);
      if (left[k] <= 0) {
        meter.ended(t + 1);
        own.push(sizes[k] * 8 / 1e3 / (t + 1 - starts[k]));
        ++done;
      }
    }
  }
  return { meter, own };
}

test('fetches in flight together are timed once: the meter reads the link, not 2-4 times it', () => {
  for (const parallel of [2, 3, 4]) {
    // 24 chunks of 30-60 kB, `parallel` of them on a 2 Mbps link at a time, staggered.
    const sizes = Array.from({ length: 24 }, (_, k) => 30000 + 1250 * ((k * 7) % 24));
    const starts = [];
    let t = 0;
    for (let k = 0; k < sizes.length; ++k) {
      starts.push(t);
      t += Math.round(sizes[k] * 8 / 2e3 / parallel);  // a new fetch as each share ends
    }
    const { meter, own } = simulate(2, starts, sizes);
    const estimate = meter.estimate(1e9);
    // Within 3 %: the link's last partial millisecond of each fetch is counted busy.
    assert.ok(Math.abs(estimate - 2) <= 0.06, `${parallel} in flight: ${estimate} Mbps`);
    // The fetches were on the link together: each one's own rate is a share of it.
    assert.ok(Math.min(...own) < 2 / parallel * 1.5, `${parallel} in flight: ${own}`);
  }
});
