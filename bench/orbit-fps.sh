#!/usr/bin/env bash
# Frames per second of a camera orbit with data resident: MODES ("in-process" and/or worker
# counts, default "in-process 2") each render an ORBIT-frame orbit (default 120) of SCENE on
# one engine / one cluster, one after the other in the same run. Reports the first frame
# (stores opened, pages loaded cold) and the steady state (median of frames 1..) separately,
# with frames/s, samples per frame and peak RSS (GNU time). Raw stats under $OUT.
#
#   bench/orbit-fps.sh [SCENE] [extra coordinator render flags...]
#
# Environment: MODES ("in-process 2"), ORBIT (120), SIZE (1280x720), OUT (target/orbit-fps),
# COORDINATOR (a built coordinator; default: build the release one).
set -euo pipefail
cd "$(dirname "$0")/.."
SCENE="${1:-configs/demo.toml}"
shift || true
MODES="${MODES:-in-process 2}"
ORBIT="${ORBIT:-120}"
SIZE="${SIZE:-1280x720}"
OUT="${OUT:-target/orbit-fps}"
COORDINATOR="${COORDINATOR:-}"
if [ -z "$COORDINATOR" ]; then
  cargo build --release -p strata-coordinator --bin coordinator
  COORDINATOR=./target/release/coordinator
fi
mkdir -p "$OUT"
# Generate the scene's synthetic survey first, so no mode pays for it.
"$COORDINATOR" -q render "$SCENE" --in-process --size 8x8 -o "$OUT/warm.png" >/dev/null
for m in $MODES; do
  if [ "$m" = in-process ]; then mode=(--in-process); else mode=(--workers "$m"); fi
  rm -rf "$OUT/$m" && mkdir -p "$OUT/$m"
  # Every mode's first frame reads its pages cold, not from an earlier mode's page cache.
  python3 bench/drop-page-cache.py "$SCENE"
  /usr/bin/time -v -o "$OUT/$m.time" "$COORDINATOR" -q render "$SCENE" "${mode[@]}" \
    --size "$SIZE" --orbit "$ORBIT" -o "$OUT/$m/f_%05d.png" --stats "$OUT/$m.jsonl" "$@" >/dev/null 2>&1
done
python3 - "$OUT" $MODES <<'PY'
import json, re, statistics, sys
out, modes = sys.argv[1], sys.argv[2:]
print("| mode | frames | first frame s | steady state: median s per frame | frames/s | p90 s | samples/frame (M) | peak RSS (MB) |")
print("|---|---|---|---|---|---|---|---|")
for m in modes:
    rows = [json.loads(l) for l in open(f"{out}/{m}.jsonl")]
    fr = [r for r in rows if r["kind"] == "frame"]
    secs = [f["seconds"] for f in fr]
    rest = sorted(secs[1:])
    med = statistics.median(rest)
    p90 = rest[int(0.9 * (len(rest) - 1))]
    samples = statistics.median([f["samples"] for f in fr[1:]]) / 1e6
    rss = max(int(x) for x in re.findall(r"Maximum resident set size \(kbytes\): (\d+)", open(f"{out}/{m}.time").read())) / 1024
    name = m if m == "in-process" else f"{m} workers"
    print(f"| {name} | {len(secs)} | {secs[0]:.2f} | {med:.3f} | {1 / med:.2f} | {p90:.3f} | {samples:.1f} | {rss:.0f} |")
PY
