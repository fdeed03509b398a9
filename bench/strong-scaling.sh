#!/usr/bin/env bash
# Strong scaling of a camera orbit over one scene: p = 1, 2, 4, 8 worker processes with a
# fixed number of rayon threads each (`cluster.worker_threads`, default 2), so p workers on
# one machine stand in for p nodes. Every p renders the same orbit on one cluster; frame 0
# loads the data, the later frames run with it resident and are the ones compared.
#
# Reports per p: median frame time over frames 1.., speed-up and efficiency against p = 1,
# samples per frame and their inflation over p = 1 (early termination is per region), the
# imbalance (slowest / mean worker render time) and bytes moved per frame (exchange +
# gather) and the peak RSS of the largest process (GNU time: the coordinator or a worker).
# Writes the table to stdout and the raw stats under $OUT (default
# target/strong-scaling).
#
#   bench/strong-scaling.sh [SCENE] [extra coordinator render flags...]
#
# Environment: PS ("1 2 4 8"), FRAMES (4), SIZE (1280x720), THREADS (2).
# On a GPU-less node without a Rust toolchain: build here, carry target/release/coordinator
# and set COORDINATOR to it.
set -euo pipefail
cd "$(dirname "$0")/.."
SCENE="${1:-configs/demo.toml}"
shift || true
PS="${PS:-1 2 4 8}"
FRAMES="${FRAMES:-4}"
SIZE="${SIZE:-1280x720}"
THREADS="${THREADS:-2}"
OUT="${OUT:-target/strong-scaling}"
COORDINATOR="${COORDINATOR:-}"
if [ -z "$COORDINATOR" ]; then
  cargo build --release -p strata-coordinator --bin coordinator
  COORDINATOR=./target/release/coordinator
fi
mkdir -p "$OUT"
for p in $PS; do
  rm -f "$OUT"/p"$p"_*.png
  /usr/bin/time -v -o "$OUT/p$p.time" "$COORDINATOR" -q render "$SCENE" \
    -o "$OUT/p${p}_%03d.png" --orbit "$FRAMES" --workers "$p" --size "$SIZE" \
    --set "cluster.worker_threads=$THREADS" --stats "$OUT/p$p.jsonl" "$@"
done
python3 - "$OUT" $PS <<'EOF'
import json, statistics, sys, re
out, ps = sys.argv[1], [int(p) for p in sys.argv[2:]]
rows = {}
for p in ps:
    lines = [json.loads(l) for l in open(f"{out}/p{p}.jsonl")]
    frames = [l for l in lines if l["kind"] == "frame"]
    workers = [l for l in lines if l["kind"] == "worker"]
    warm = [f for f in frames if f["frame"] > 0] or frames
    t = statistics.median(f["seconds"] for f in warm)
    samples = statistics.median(f["samples"] for f in warm)
    imb = []
    moved = []
    for f in warm:
        ws = [w for w in workers if w["frame"] == f["frame"]]
        r = [w["render_s"] for w in ws]
        imb.append(max(r) / (sum(r) / len(r)))
        moved.append(sum(w["bytes_sent"] + w["gather_bytes"] for w in ws))
    rss = 0
    for l in open(f"{out}/p{p}.time"):
        m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", l)
        if m:
            rss = int(m.group(1)) / 1024
    rows[p] = (t, samples, statistics.median(imb), statistics.median(moved), rss)
base = rows[ps[0]]
print("| p | frame time (frames 1..) | speed-up | efficiency | samples/frame | inflation | imbalance (max/mean render) | MB moved/frame | largest process peak RSS MiB |")
print("|---|---|---|---|---|---|---|---|---|")
for p in ps:
    t, s, imb, mv, rss = rows[p]
    sp = base[0] / t * ps[0]
    print(f"| {p} | {t*1e3:.0f} ms | {sp:.2f} | {sp/p*100:.0f} % | {s/1e6:.1f} M | {(s/base[1]-1)*100:+.1f} % | {imb:.2f} | {mv/1e6:.1f} | {rss:.0f} |")
EOF
