#!/usr/bin/env bash
# Strong scaling of a camera orbit over one scene: p = 1, 2, 4, 8 worker processes with a
# fixed number of rayon threads each (`cluster.worker_threads`, default 2), so p workers on
# one machine stand in for p nodes. Every p renders the first FRAMES frames of an
# ORBIT-frame orbit on one cluster, with cross-worker occlusion on and off (MODES), one after
# the other in the same run; frame 0 loads the data, the later frames run with it resident
# and are the ones compared.
#
# Reports per p and mode: median frame time over frames 1.., speed-up and efficiency against
# the first p of the same mode, samples per frame and their inflation over the first p of
# the first mode, rays per frame (early termination is per region unless occlusion tells a worker what lies
# in front), blocks left out and re-cast by occlusion, the imbalance (slowest / mean worker
# render time, the same of their render CPU time and of their samples, which
# oversubscribed cores do not blur), the re-splits over the run, the CPU time all workers spent per frame (and in their
# renders) and its ratio to the first p's (the work distribution adds, which sharing cores
# does not inflate, unlike wall times), bytes moved per frame (exchange + gather) and the peak RSS of the largest
# process (GNU time: the coordinator or a worker). Writes the table to stdout and the raw
# stats under $OUT (default target/strong-scaling).
#
#   bench/strong-scaling.sh [SCENE] [extra coordinator render flags...]
#
# Environment: PS ("1 2 4 8"), FRAMES (4), ORBIT (120), SIZE (1280x720), THREADS (2),
# MODES ("on off").
# On a GPU-less node without a Rust toolchain: build here, carry target/release/coordinator
# and set COORDINATOR to it; where GNU time is not installed, carry /usr/bin/time and set
# TIME_BIN to it.
set -euo pipefail
cd "$(dirname "$0")/.."
SCENE="${1:-configs/demo.toml}"
shift || true
PS="${PS:-1 2 4 8}"
FRAMES="${FRAMES:-4}"
ORBIT="${ORBIT:-120}"
MODES="${MODES:-on off}"
SIZE="${SIZE:-1280x720}"
THREADS="${THREADS:-2}"
OUT="${OUT:-target/strong-scaling}"
COORDINATOR="${COORDINATOR:-}"
TIME_BIN="${TIME_BIN:-/usr/bin/time}"
if [ -z "$COORDINATOR" ]; then
  cargo build --release -p strata-coordinator --bin coordinator
  COORDINATOR=./target/release/coordinator
fi
mkdir -p "$OUT"
for mode in $MODES; do
  occ=true
  [ "$mode" = off ] && occ=false
  for p in $PS; do
    rm -f "$OUT"/"$mode"_p"$p"_*.png
    "$TIME_BIN" -v -o "$OUT/${mode}_p$p.time" "$COORDINATOR" -q render "$SCENE" \
      -o "$OUT/${mode}_p${p}_%03d.png" --orbit "$ORBIT" --frames "0..$FRAMES" --workers "$p" \
      --size "$SIZE" --set "cluster.worker_threads=$THREADS" --set "cluster.occlusion=$occ" \
      --stats "$OUT/${mode}_p$p.jsonl" "$@"
  done
done
python3 - "$OUT" "$MODES" $PS <<'EOF'
import json, statistics, sys, re
out, modes, ps = sys.argv[1], sys.argv[2].split(), [int(p) for p in sys.argv[3:]]
print("| occlusion | p | frame time (frames 1..) | speed-up | efficiency | samples/frame | inflation | rays/frame | workers' CPU/frame (render) | work over the first p | blocks left out / re-cast | imbalance (max/mean render) | imbalance of work (render CPU) | imbalance of samples | re-splits | MB moved/frame | largest process peak RSS MiB |")
print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
base_samples = None
for mode in modes:
    rows = {}
    for p in ps:
        lines = [json.loads(l) for l in open(f"{out}/{mode}_p{p}.jsonl")]
        frames = [l for l in lines if l["kind"] == "frame"]
        workers = [l for l in lines if l["kind"] == "worker"]
        warm = [f for f in frames if f["frame"] > 0] or frames
        t = statistics.median(f["seconds"] for f in warm)
        samples = statistics.median(f["samples"] for f in warm)
        rays = statistics.median(sum(w.get("rays", 0) for w in workers if w["frame"] == f["frame"]) for f in warm)
        occ = statistics.median(f.get("occluded_blocks", 0) for f in warm)
        fix = statistics.median(f.get("fixup_blocks", 0) for f in warm)
        imb = []
        cimb = []
        simb = []
        cpu = []
        rcpu = []
        moved = []
        for f in warm:
            ws = [w for w in workers if w["frame"] == f["frame"]]
            r = [w["render_s"] for w in ws]
            imb.append(max(r) / (sum(r) / len(r)) if r else 1.0)
            c = [w.get("render_cpu_s", 0) for w in ws]
            cimb.append(max(c) / (sum(c) / len(c)) if c and sum(c) > 0 else 1.0)
            n = [w["samples"] for w in ws]
            simb.append(max(n) / (sum(n) / len(n)) if n and sum(n) > 0 else 1.0)
            moved.append(sum(w["bytes_sent"] + w["gather_bytes"] for w in ws))
            cpu.append(sum(w.get("cpu_s", 0) for w in ws))
            rcpu.append(sum(w.get("render_cpu_s", 0) for w in ws))
        splits = sum(1 for l in lines if l["kind"] == "rebalance")
        rss = 0
        for l in open(f"{out}/{mode}_p{p}.time"):
            m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", l)
            if m:
                rss = int(m.group(1)) / 1024
        rows[p] = (t, samples, occ, fix, statistics.median(imb), statistics.median(simb), splits, statistics.median(moved), rss, statistics.median(cpu), statistics.median(rcpu), rays, statistics.median(cimb))
    base = rows[ps[0]]
    if base_samples is None:
        base_samples = base[1]
    for p in ps:
        t, s, occ, fix, imb, simb, splits, mv, rss, cpu, rcpu, rays, cimb = rows[p]
        sp = base[0] / t * ps[0]
        work = f"{cpu/base[9]:.2f}×" if base[9] > 0 else "–"
        print(f"| {mode} | {p} | {t*1e3:.0f} ms | {sp:.2f} | {sp/p*100:.0f} % | {s/1e6:.1f} M | {(s/base_samples-1)*100:+.1f} % | {rays/1e6:.2f} M | {cpu*1e3:.0f} ms ({rcpu*1e3:.0f}) | {work} | {occ:.0f} / {fix:.0f} | {imb:.2f} | {cimb:.2f} | {simb:.2f} | {splits} | {mv/1e6:.1f} | {rss:.0f} |")

# Where a frame's time goes: medians over frames 1.. of the slowest worker's phases and of
# the mean worker's render (the gap between the two is the imbalance), in milliseconds.
# `render` includes its feedback rounds and loads; `occlusion` is the exchange of the
# transmittance maps, which waits for the slowest worker's render; `composite` is the
# exchange and blend, which waits for the slowest re-cast; `after the last render` is the
# frame minus the slowest render (the maps of the workers behind it, their re-casts and the
# exchange: what occlusion adds to the frame's critical path); the slowest render's worker's
# own wait for its map and re-cast follow; `rounds` the most feedback rounds a worker
# needed.
print()
print("| occlusion | p | frame | render, slowest / mean | of it loads, slowest | occlusion maps | re-cast | composite | after the last render | its worker's map wait / re-cast | rounds |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for mode in modes:
    for p in ps:
        lines = [json.loads(l) for l in open(f"{out}/{mode}_p{p}.jsonl")]
        frames = [l for l in lines if l["kind"] == "frame" and l["frame"] > 0]
        workers = [l for l in lines if l["kind"] == "worker"]
        cols = {k: [] for k in ("frame", "rmax", "rmean", "load", "occ", "fix", "comp", "post", "sw", "sf", "rounds")}
        for f in frames:
            ws = [w for w in workers if w["frame"] == f["frame"]]
            if not ws:
                continue
            mx = lambda k: max(w.get(k, 0) for w in ws)
            cols["frame"].append(f["seconds"])
            cols["rmax"].append(mx("render_s"))
            cols["rmean"].append(sum(w["render_s"] for w in ws) / len(ws))
            cols["load"].append(mx("load_s"))
            cols["occ"].append(mx("occlusion_s"))
            cols["fix"].append(mx("fixup_s"))
            cols["comp"].append(mx("composite_s"))
            cols["rounds"].append(mx("render_rounds"))
            slowest = max(ws, key=lambda w: w["render_s"])
            cols["post"].append(f["seconds"] - slowest["render_s"])
            cols["sw"].append(slowest.get("occlusion_s", 0))
            cols["sf"].append(slowest.get("fixup_s", 0))
        m = {k: statistics.median(v) if v else 0 for k, v in cols.items()}
        print(f"| {mode} | {p} | {m['frame']*1e3:.0f} | {m['rmax']*1e3:.0f} / {m['rmean']*1e3:.0f} | {m['load']*1e3:.0f} | {m['occ']*1e3:.0f} | {m['fix']*1e3:.0f} | {m['comp']*1e3:.0f} | {m['post']*1e3:.0f} | {m['sw']*1e3:.0f} / {m['sf']*1e3:.0f} | {m['rounds']:.0f} |")
EOF
