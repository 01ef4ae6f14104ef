// Drives the holocap player in headless Chromium (Debian's `chromium`, WebGL2 through
// SwiftShader) through the DevTools protocol, for tests/playback/web_test.cc and bench/web_bench.
//
//   node drive.mjs shots URL OUT W H FRAME CAMERA STREAM...   one PNG per stream (OUT/STREAM.png)
//                                                             of capture camera CAMERA at FRAME,
//                                                             the subject alone (background=0)
//   node drive.mjs camera URL OUT W H FRAME CAMERA STREAM...  the same with each stream's
//                                                             background behind the subject, as
//                                                             a viewer sees it
//   node drive.mjs interact URL OUT BROKEN_FRAME             drag, zoom, play, scrub, a broken
//                                                             chunk, an unknown version, the
//                                                             player's picture (OUT/player.png)
//   node drive.mjs scrub URL OUT W H CAMERA STREAM FRAME...  opens STREAM at the first FRAME through
//                                                             capture camera CAMERA, scrubs the
//                                                             timeline to each next FRAME in turn
//                                                             (OUT/scrub-FRAME.png each)
//   node drive.mjs refused URL OUT FRAME STREAM               the messages the page shows for
//                                                             FRAME of STREAM once it names a
//                                                             problem (a chunk it cannot play)
//   node drive.mjs bench URL OUT STREAM...                    time to first frame and frames
//                                                             decoded per second per stream
//   node drive.mjs ladder URL OUT LADDER SPEED MBPS LATENCY_MS BUFFER
//                                                             plays LADDER adaptively at SPEED,
//                                                             fetching BUFFER frames ahead: up
//                                                             to its top level, the connection
//                                                             throttled to MBPS (LATENCY_MS: down
//                                                             a level, held there two loops), then
//                                                             freed again; the levels, switches
//                                                             and stalls the page reports
//   node drive.mjs playback URL OUT W H MBPS LATENCY_MS STREAM...
//                                                             per stream at W x H: time to first
//                                                             frame over a link of MBPS and
//                                                             LATENCY_MS, frames drawn and shown
//                                                             per second playing it (5 s), decode
//                                                             ms per frame
//   node drive.mjs meter URL OUT MBPS LATENCY_MS PARALLEL STREAM
//                                                             the page's ThroughputMeter over
//                                                             STREAM's chunks fetched PARALLEL
//                                                             at a time through its StreamBuffer,
//                                                             the link throttled to MBPS and
//                                                             LATENCY_MS; each fetch's interval
//                                                             and bytes beside the meter's figure
//   node drive.mjs picture URL OUT W H STREAM                 the whole page, its bar shown, at
//                                                             frame 0 of STREAM (OUT/player.png;
//                                                             the documentation's picture)
// Each writes OUT/<mode>.json, with every console error and page error seen.
import fs from 'node:fs';
import path from 'node:path';
import puppeteer from 'puppeteer-core';

const [mode, url, out, ...rest] = process.argv.slice(2);
const consoleErrors = [];
const browser = await puppeteer.launch({
  executablePath: process.env.HOLOCAP_CHROMIUM || '/usr/bin/chromium',
  headless: true,
  args: ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
         '--ignore-gpu-blocklist', '--disable-dev-shm-usage'],
});

async function open(hash, width, height, intercept, prepare) {
  const page = await browser.newPage();
  if (prepare) await prepare(page);
  await page.setViewport({ width, height, deviceScaleFactor: 1 });
  page.on('console', (m) => { if (m.type() === 'error') consoleErrors.push(`${m.text()} (${m.location()?.url ?? ''})`); });
  page.on('pageerror', (e) => consoleErrors.push(`page error: ${e.message}`));
  if (intercept) {
    await page.setRequestInterception(true);
    page.on('request', intercept);
  }
  await page.goto(`${url}#${hash}`, { waitUntil: 'load' });
  return page;
}

const state = (page) => page.evaluate(() => {
  const s = window.holocap;
  return { frame: s.frame, drawnFrame: s.drawnFrame, drawnStream: s.drawnStream,
           drawnState: s.drawnState, playing: s.playing, messages: s.messages, fatal: s.fatal,
           hash: window.location.hash, timeToFirstFrameMs: s.timeToFirstFrameMs, stats: s.stats,
           drawnBackground: s.drawnBackground };
});

async function waitFor(page, predicate, what, timeoutMs = 60000) {
  const start = Date.now();
  for (;;) {
    const s = await state(page);
    if (predicate(s)) return s;
    if (Date.now() - start > timeoutMs) throw new Error(`timed out waiting for ${what}: ${JSON.stringify(s)}`);
    await new Promise((r) => setTimeout(r, 50));
  }
}

async function shots([width, height, frame, camera, ...streams], background) {
  const results = {};
  for (const stream of streams) {
    const page = await open(`frame=${frame}&camera=${camera}&stream=${stream}&helpers=0&ui=0` +
                            (background ? '' : '&background=0'), +width, +height);
    const s = await waitFor(page, (s) => s.drawnFrame === +frame && s.drawnStream === stream, `${stream} frame ${frame}`);
    // Two more animation frames: the drawn frame is on the canvas.
    await page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
    const file = path.join(out, `${stream}.png`);
    await page.screenshot({ path: file, clip: { x: 0, y: 0, width: +width, height: +height } });
    results[stream] = { file, state: s.drawnState, background: s.drawnBackground, messages: s.messages };
    await page.close();
  }
  return results;
}

async function interact([brokenFrame]) {
  const results = {};
  const page = await open('frame=0', 640, 480);
  await waitFor(page, (s) => s.drawnFrame === 0 && s.drawnState === 'ready', 'the first frame');
  const picture = async () => Buffer.from(await page.screenshot({ encoding: 'binary' }));
  const before = await state(page);
  const shot0 = await picture();
  // Orbit: a drag across the canvas.
  await page.mouse.move(320, 240);
  await page.mouse.down();
  for (let i = 1; i <= 10; ++i) await page.mouse.move(320 + 12 * i, 240 + 3 * i);
  await page.mouse.up();
  await page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
  const dragged = await state(page);
  const shot1 = await picture();
  results.drag = { hashBefore: before.hash, hashAfter: dragged.hash, pictureChanged: !shot0.equals(shot1) };
  // Zoom: the wheel.
  await page.mouse.move(320, 240);
  await page.mouse.wheel({ deltaY: -400 });
  await page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
  const zoomed = await state(page);
  const shot2 = await picture();
  results.zoom = { hashBefore: dragged.hash, hashAfter: zoomed.hash, pictureChanged: !shot1.equals(shot2) };
  await page.screenshot({ path: path.join(out, 'player.png') });
  // Play: the button, then the frame index moves on.
  await page.click('#play');
  const played = await waitFor(page, (s) => s.frame !== 0, 'playback to move', 30000);
  results.play = { frameAfter: played.frame, playing: played.playing };
  // Scrub: the timeline set to the last frame.
  const last = await page.evaluate(() => {
    const t = document.getElementById('timeline');
    t.value = t.max;
    t.dispatchEvent(new Event('input', { bubbles: true }));
    return Number(t.max);
  });
  const scrubbed = await waitFor(page, (s) => s.drawnFrame === last, 'the scrubbed frame');
  results.scrub = { target: last, frame: scrubbed.frame, drawnFrame: scrubbed.drawnFrame, playing: scrubbed.playing };
  await page.close();
  // A broken chunk: playback reports it and goes on to the frames after it.
  const broken = await open(`frame=0&play=1&loop=0&stream=${rest[1] ?? ''}`, 320, 240);
  const passed = await waitFor(broken, (s) => s.frame > +brokenFrame && s.drawnFrame > +brokenFrame,
                               'playback past the broken chunk');
  results.broken = { messages: passed.messages, frame: passed.frame };
  await broken.close();
  // A site of an unknown format version is refused.
  const refused = await open('', 320, 240, (request) => {
    if (request.url().endsWith('/manifest.json')) {
      request.respond({ status: 200, contentType: 'application/json',
                        body: JSON.stringify({ format: 'holocap-stream', version: 99, frames: [], streams: [] }) });
    } else {
      request.continue();
    }
  });
  results.unknownVersion = await waitFor(refused, (s) => s.fatal !== null, 'the refusal').then((s) => s.fatal);
  await refused.close();
  return results;
}

async function scrub([width, height, camera, stream, first, ...targets]) {
  const page = await open(`frame=${first}&camera=${camera}&stream=${stream}&helpers=0&ui=0&background=0`, +width, +height);
  await waitFor(page, (s) => s.drawnFrame === +first && s.drawnState === 'ready', `${stream} frame ${first}`);
  const results = { first: +first, frames: [] };
  for (const target of targets.map(Number)) {
    await page.evaluate((frame) => {
      const t = document.getElementById('timeline');
      t.value = String(frame);
      t.dispatchEvent(new Event('input', { bubbles: true }));
    }, target);
    const s = await waitFor(page, (s) => s.drawnFrame === target && s.drawnState === 'ready', `scrubbed to ${target}`);
    await page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
    const file = path.join(out, `scrub-${target}.png`);
    await page.screenshot({ path: file, clip: { x: 0, y: 0, width: +width, height: +height } });
    results.frames.push({ target, frame: s.frame, drawnFrame: s.drawnFrame, state: s.drawnState,
                          messages: s.messages, file });
  }
  await page.close();
  return results;
}

async function picture([width, height, stream]) {
  const page = await open(`frame=0&stream=${stream}`, +width, +height);
  const s = await waitFor(page, (s) => s.drawnFrame === 0 && s.drawnStream === stream && s.drawnState === 'ready', `${stream} frame 0`);
  await page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
  const file = path.join(out, 'player.png');
  await page.screenshot({ path: file });
  await page.close();
  return { file, state: s.drawnState, messages: s.messages };
}

async function bench(streams) {
  const results = {};
  for (const stream of streams) {
    const page = await open(`frame=0&stream=${stream}&helpers=0`, 640, 480);
    const s = await waitFor(page, (s) => s.drawnStream === stream && s.timeToFirstFrameMs !== null, `${stream} first frame`, 120000);
    const decode = await page.evaluate((name) => window.holocap.benchDecode(name), stream);
    results[stream] = { timeToFirstFrameMs: s.timeToFirstFrameMs, ...decode };
    await page.close();
  }
  return results;
}

async function ladder([name, speed, mbps, latencyMs, buffer]) {
  const page = await open(`frame=0&stream=${name}&level=auto&play=1&speed=${speed}&buffer=${buffer}` +
                          '&helpers=0', 320, 240);
  const client = await page.createCDPSession();
  await client.send('Network.enable');
  const abr = () => page.evaluate(() => {
    const s = window.holocap;
    return { ...s.abr, pending: undefined, frame: s.frame, fatal: s.fatal, messages: s.messages,
             levels: s.ladders.find((l) => l.name === s.abr.ladder)?.levels.map((l) => l.stream),
             dataset: { ...document.body.dataset } };
  });
  const until = async (predicate, what, timeoutMs = 120000) => {
    const start = Date.now();
    for (;;) {
      const a = await abr();
      if (a.stream !== undefined && predicate(a)) return a;
      if (a.fatal || Date.now() - start > timeoutMs)
        throw new Error(`timed out waiting for ${what}: ${JSON.stringify(a)}`);
      await new Promise((r) => setTimeout(r, 50));
    }
  };
  // Each phase's longest stall: the page's figure, cleared as the phase begins.
  const newPhase = () => page.evaluate(() => { window.holocap.abr.longestStallFrames = 0; });
  const phase = (a, since) => ({ stream: a.stream, mbps: a.mbps, throughputMbps: a.throughputMbps,
                                 framesPlayed: a.framesPlayed, framesSince: a.framesPlayed - since,
                                 stalls: a.stalls, longestStallFrames: a.longestStallFrames,
                                 dataset: a.dataset });
  const first = await until((a) => a.levels !== undefined, 'the ladder');
  const top = first.levels[first.levels.length - 1];
  const results = { levels: first.levels, frames: await page.evaluate(() => window.holocap.manifest.frames.length) };
  // Up the ladder on the open connection.
  const opened = await until((a) => a.stream === top, `the top level ${top}`);
  results.open = phase(opened, 0);
  // Throttled: down to a level whose rate at this speed fits, then held there for two loops.
  const throttle = (download, latency) => client.send('Network.emulateNetworkConditions', {
    offline: false, latency, downloadThroughput: download, uploadThroughput: download });
  await throttle(+mbps * 1e6 / 8, +latencyMs);
  await newPhase();
  const throttledAt = (await abr()).framesPlayed;
  const down = await until((a) => a.stream !== top, `a level below ${top}`, 60000);
  results.down = phase(down, throttledAt);
  await newPhase();
  let highest = 0;
  const held = await until((a) => {
    highest = Math.max(highest, a.mbps);
    return a.framesPlayed >= down.framesPlayed + 2 * results.frames;
  }, 'two loops throttled');
  results.held = { ...phase(held, down.framesPlayed), highestMbps: highest };
  // Free again: back up to the top level.
  await throttle(-1, 0);
  await newPhase();
  const freedAt = held.framesPlayed;
  const up = await until((a) => a.stream === top, `the top level ${top} again`);
  results.up = phase(up, freedAt);
  results.switches = up.switches;
  results.messages = up.messages;
  await page.close();
  return results;
}

async function meter([mbps, latencyMs, parallel, name]) {
  // The manifest as the page (its modules load from the site), nothing of the player running.
  const page = await browser.newPage();
  page.on('pageerror', (e) => consoleErrors.push(`page error: ${e.message}`));
  await page.goto(new URL('manifest.json', url).href, { waitUntil: 'load' });
  const client = await page.createCDPSession();
  await client.send('Network.enable');
  await client.send('Network.setCacheDisabled', { cacheDisabled: true });
  await client.send('Network.emulateNetworkConditions', {
    offline: false, latency: +latencyMs, downloadThroughput: +mbps * 1e6 / 8,
    uploadThroughput: +mbps * 1e6 / 8 });
  const results = await page.evaluate(async (parallel, name) => {
    const { ThroughputMeter } = await import('./player/ladder.js');
    const { StreamBuffer } = await import('./player/stream.js');
    const manifest = await (await fetch('manifest.json')).json();
    const stream = manifest.streams.find((s) => s.name === name);
    const meter = new ThroughputMeter();
    const buffer = new StreamBuffer(new URL('.', location.href), stream, (i, e) => { throw new Error(e); },
                                    () => {}, meter);
    // Each fetch's body: its interval (as the meter times it) and bytes.
    const fetches = [], body = buffer.body.bind(buffer);
    buffer.body = async (response) => {
      const start = performance.now(), bytes = await body(response);
      fetches.push({ start, end: performance.now(), bytes: bytes.byteLength });
      return bytes;
    };
    const indices = stream.chunks.map((c, i) => (c ? i : -1)).filter((i) => i >= 0);
    const t0 = performance.now();
    let next = 0, inFlight = 0, maxInFlight = 0;
    await new Promise((resolve, reject) => {
      const more = () => {
        while (inFlight < parallel && next < indices.length) {
          const i = indices[next++];
          maxInFlight = Math.max(maxInFlight, ++inFlight);
          buffer.decoded(i).then(() => { --inFlight; if (next < indices.length) more(); else if (inFlight === 0) resolve(); },
                                 reject);
        }
      };
      more();
    });
    const t1 = performance.now();
    // Each fetch's own rate (its chunk's bytes over its own interval): what summing or taking
    // the best of per-fetch rates would make of the link.
    const perFetch = fetches.map((f) => f.bytes * 8 / 1e3 / (f.end - f.start));
    // The most fetches whose bodies were on the link at once.
    const edges = fetches.flatMap((f) => [[f.start, 1], [f.end, -1]]).sort((a, b) => a[0] - b[0] || a[1] - b[1]);
    let overlap = 0, maxOverlap = 0;
    for (const [, d] of edges) maxOverlap = Math.max(maxOverlap, overlap += d);
    const bytes = indices.reduce((s, i) => s + stream.chunks[i].bytes, 0);
    return { chunks: indices.length, bytes, parallel, maxInFlight, maxOverlap,
             meterMbps: meter.estimate(), meterBusyMbps: meter.bytes * 8 / 1e3 / meter.busyMs,
             wallMbps: bytes * 8 / 1e3 / (t1 - t0),
             perFetchMeanMbps: perFetch.reduce((a, b) => a + b, 0) / perFetch.length,
             perFetchBestMbps: Math.max(...perFetch) };
  }, +parallel, name);
  await page.close();
  return { mbps: +mbps, latencyMs: +latencyMs, ...results };
}

async function playback([width, height, mbps, latencyMs, ...streams]) {
  const results = {};
  const throttled = async (page) => {
    const client = await page.createCDPSession();
    await client.send('Network.enable');
    await client.send('Network.emulateNetworkConditions', {
      offline: false, latency: +latencyMs, downloadThroughput: +mbps * 1e6 / 8,
      uploadThroughput: +mbps * 1e6 / 8 });
  };
  for (const stream of streams) {
    const first = await open(`frame=0&stream=${stream}&helpers=0`, +width, +height, null, throttled);
    const s = await waitFor(first, (s) => s.drawnStream === stream && s.timeToFirstFrameMs !== null,
                            `${stream} first frame`, 300000);
    await first.close();
    const page = await open(`frame=0&stream=${stream}&helpers=0&play=1`, +width, +height);
    await waitFor(page, (s) => s.drawnStream === stream && s.drawnState === 'ready', `${stream} playing`, 120000);
    const count = () => page.evaluate(() => ({ played: window.holocap.abr.framesPlayed, fps: window.holocap.stats.fps,
                                                t: performance.now() }));
    const start = await count();
    const drawn = [];
    for (let i = 0; i < 5; ++i) {
      await new Promise((r) => setTimeout(r, 1000));
      drawn.push((await count()).fps);
    }
    const end = await count();
    const decode = await page.evaluate((name) => window.holocap.benchDecode(name), stream);
    results[stream] = { timeToFirstFrameMs: s.timeToFirstFrameMs, mbps, latencyMs,
                        drawnPerSecond: drawn.reduce((a, b) => a + b, 0) / drawn.length,
                        shownPerSecond: (end.played - start.played) / ((end.t - start.t) / 1000),
                        decodeMsPerFrame: decode.decodeSeconds * 1000 / decode.frames, decode };
    await page.close();
  }
  return results;
}

async function refused([frame, stream]) {
  const page = await open(`frame=${frame}&stream=${stream}&helpers=0&ui=0`, 320, 240);
  const s = await waitFor(page, (s) => s.messages.length > 0, `a message about ${stream}`);
  await page.close();
  return { messages: s.messages, drawnFrame: s.drawnFrame };
}

let results;
try {
  if (mode === 'shots') results = await shots(rest, false);
  else if (mode === 'camera') results = await shots(rest, true);
  else if (mode === 'interact') results = await interact(rest);
  else if (mode === 'scrub') results = await scrub(rest);
  else if (mode === 'bench') results = await bench(rest);
  else if (mode === 'refused') results = await refused(rest);
  else if (mode === 'picture') results = await picture(rest);
  else if (mode === 'ladder') results = await ladder(rest);
  else if (mode === 'playback') results = await playback(rest);
  else if (mode === 'meter') results = await meter(rest);
  else throw new Error(`unknown mode '${mode}'`);
  results.ok = true;
} catch (error) {
  results = { ok: false, error: String(error && error.stack || error) };
}
results.consoleErrors = consoleErrors;
fs.writeFileSync(path.join(out, `${mode}.json`), JSON.stringify(results, null, 1));
await browser.close();
console.log(JSON.stringify(results));
