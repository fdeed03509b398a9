#!/usr/bin/env bash
# Powerwall frames: a camera orbit over configs/wall.toml (a 3×2 wall of 1920×1080 tiles with
# 40-pixel bezels, 12.4 MP per frame) in-process and on local workers (WS), one after the
# other in the same run. Frame 0 loads the data; frames 1.. run with it resident.
#
# Reports per run: first frame, median later frame and frames/s, samples per frame, the bytes
# each display (driving) rank receives per frame, the bytes the coordinator receives, and
# the peak RSS of the largest process (GNU time). Raw stats under $OUT.
#
#   bench/wall.sh [SCENE] [extra coordinator render flags...]
#
# Environment: WS ("2 3 6"), FRAMES (4), ORBIT (120), OUT (target/wall-bench), COORDINATOR.
set -euo pipefail
cd "$(dirname "$0")/.."
SCENE="${1:-configs/wall.toml}"
shift || true
WS="${WS:-2 3 6}"
FRAMES="${FRAMES:-4}"
ORBIT="${ORBIT:-120}"
OUT="${OUT:-target/wall-bench}"
COORDINATOR="${COORDINATOR:-}"
if [ -z "$COORDINATOR" ]; then
  cargo build --release -p strata-coordinator --bin coordinator
  COORDINATOR=./target/release/coordinator
fi
mkdir -p "$OUT"
# Generate the survey first so no run pays for it.
"$COORDINATOR" -q render "$SCENE" --in-process --set 'wall.tiles=[1,1]' --set 'wall.tile_size=[8,8]' \
  -o "$OUT/warm.png" >/dev/null
for w in 0 $WS; do
  if [ "$w" = 0 ]; then mode=(--in-process); name=in-process; else mode=(--workers "$w"); name="w$w"; fi
  rm -rf "$OUT/$name" && mkdir -p "$OUT/$name"
  # Every run's first frame reads its pages cold, not from an earlier run's page cache.
  python3 bench/drop-page-cache.py "$SCENE"
  /usr/bin/time -v -o "$OUT/$name.time" "$COORDINATOR" -q render "$SCENE" "${mode[@]}" \
    --orbit "$ORBIT" --frames "0..$FRAMES" -o "$OUT/$name/f_%05d.png" \
    --stats "$OUT/$name.jsonl" "$@" >/dev/null
done
python3 - "$OUT" $WS <<'PY'
import json, re, statistics, sys
out, ws = sys.argv[1], ["in-process"] + ["w" + w for w in sys.argv[2:]]
print("| run | first frame s | later frames: median s | frames/s | samples/frame (M) | bytes received per display rank per frame (MB) | coordinator receives (bytes) | peak RSS (MB) |")
print("|---|---|---|---|---|---|---|---|")
for name in ws:
    rows = [json.loads(l) for l in open(f"{out}/{name}.jsonl")]
    frames = [r for r in rows if r["kind"] == "frame"]
    workers = [r for r in rows if r["kind"] == "worker"]
    summary = [r for r in rows if r["kind"] == "summary"][0]
    secs = [f["seconds"] for f in frames]
    later = statistics.median(secs[1:]) if len(secs) > 1 else float("nan")
    samples = statistics.median([f["samples"] for f in frames[1:]] or [0]) / 1e6
    last = max((w["frame"] for w in workers), default=0)
    recv = sorted(
        (w["rank"], w["bytes_received"] / 1e6, w["tiles_written"])
        for w in workers if w["frame"] == last and w["tiles_written"] > 0
    )
    recv_s = ", ".join(f"rank {r}: {b:.1f} ({t} tiles)" for r, b, t in recv) or "-"
    rss = max(int(m.group(1)) for m in re.finditer(r"Maximum resident set size \(kbytes\): (\d+)", open(f"{out}/{name}.time").read())) / 1024
    gather = summary.get("gather_bytes", 0) if name != "in-process" else "-"
    print(f"| {name} | {secs[0]:.2f} | {later:.2f} | {1 / later:.2f} | {samples:.1f} | {recv_s} | {gather} | {rss:.0f} |")
PY
