#!/bin/bash
# Playback measured in the page: per stream of a site written by `holocap export web`, headless
# Chromium (WebGL2 on SwiftShader) at 1280x720 through tests/playback/browser/drive.mjs playback:
# time to first frame over a throttled link (Chromium's network emulation), frames drawn per
# second and stream frames shown per second while it plays (the page's own player, the link
# free), and decode milliseconds per frame (every chunk fetched and decoded in the page).
#
#   bench/web_playback.sh SITE OUT [MBPS LATENCY_MS]     (from the source root; 10 Mbps, 50 ms)
#
# The site is copied to OUT with this tree's player (playback/web/, what `export web` embeds),
# served by `holocap view`. Writes OUT/playback.json and prints the table.
set -euo pipefail
site=$1 out=$2 mbps=${3:-10} latency=${4:-50}
holocap=${HOLOCAP:-build/app/holocap}
rm -rf "$out"
mkdir -p "$out"
cp -r "$site" "$out/site"
cp -r playback/web/index.html playback/web/player "$out/site/"
"$holocap" view "$out/site" --port 0 > "$out/view.log" 2>&1 &
view=$!
trap 'kill $view' EXIT
url=
for _ in $(seq 100); do
  url=$(grep -o 'http://[^ ]*' "$out/view.log" | head -1 || true)
  [ -n "$url" ] && break
  sleep 0.1
done
[ -n "$url" ] || { echo "holocap view did not start: $(cat "$out/view.log")" >&2; exit 1; }
streams=$(/usr/bin/python3 -c 'import json,sys; print(" ".join(s["name"] for s in json.load(open(sys.argv[1]))["streams"]))' "$out/site/manifest.json")
node tests/playback/browser/drive.mjs playback "$url" "$out" 1280 720 "$mbps" "$latency" $streams > /dev/null
/usr/bin/python3 - "$out/playback.json" "$out/site/manifest.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
if not r.get("ok"):
    sys.exit("the page failed: " + r.get("error", ""))
m = json.load(open(sys.argv[2]))
print(f"# {len(m['frames'])} frames at {m['fps']} fps; 1280x720, SwiftShader; console errors: {len(r['consoleErrors'])}")
print(f"{'stream':<16}{'Mbps@fps':>10}{'TTFF ms':>10}{'drawn/s':>9}{'shown/s':>9}{'decode ms/frame':>17}")
for s in m["streams"]:
    p = r[s["name"]]
    print(f"{s['name']:<16}{s['mbps']:>10.2f}{p['timeToFirstFrameMs']:>10.0f}{p['drawnPerSecond']:>9.1f}"
          f"{p['shownPerSecond']:>9.1f}{p['decodeMsPerFrame']:>17.1f}")
print(f"# TTFF: from navigation to the first frame drawn over {p['mbps']} Mbps, {p['latencyMs']} ms latency")
PY
