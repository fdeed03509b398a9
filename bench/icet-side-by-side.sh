#!/usr/bin/env bash
# IceT 2.2's SimpleTiming and Strata's bench-composite on the same machine, in the same
# session, interleaved round by round: ordered float blending of 1920x1080 frames at
# p = 2, 4, 8, dense and sparse, IceT over MPI shared memory and Strata over its
# shared-memory transport.
#
#   bench/icet-side-by-side.sh ICET_SRC OUT_DIR [ROUNDS] [FRAMES]
#   (STRATA_FRAMES, default 7: bench-composite's timed frames per configuration)
#
# ICET_SRC is an IceT source tree (the baselines in ../shared/baselines/RESULTS.md used
# wilsonCernWq/icet @088aa5a26137). It is copied to OUT_DIR, given SimpleTiming's `-direct`
# flag (ICET_STRATEGY_DIRECT, as the baselines' local change did) and built with its MPI
# layer only. Needs cmake, a C compiler and MPI (Debian: cmake libopenmpi-dev openmpi-bin)
# and a release bench-composite (cargo build --release -p strata-bench).
#
# IceT runs as the baselines did (`-transparent`, `-seed 12345`, sparse images interlaced,
# `-dense-images` for dense), FRAMES frames; frame 0 is dropped and the median of the others
# kept. Strata runs `bench-composite --transports shm` (its own median of STRATA_FRAMES
# timed frames after a warm-up). Each
# round runs every IceT configuration, then Strata; the summary keeps, per configuration,
# the lowest of the rounds' medians, and writes OUT_DIR/summary.md.
set -euo pipefail
SRC=${1:?IceT source tree}
OUT=${2:?output folder}
ROUNDS=${3:-2}
FRAMES=${4:-21}
STRATA_FRAMES=${STRATA_FRAMES:-7}
BENCH=${BENCH:-target/release/bench-composite}
[ -x "$BENCH" ] || { echo "error: $BENCH missing (cargo build --release -p strata-bench)" >&2; exit 1; }
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)

if [ ! -x "$OUT/icet-build/bin/icetTests_mpi" ]; then
  rm -rf "$OUT/icet-src"
  cp -r "$SRC" "$OUT/icet-src"
  python3 - "$OUT/icet-src/tests/SimpleTiming.c" <<'EOF'
import sys
p = sys.argv[1]
s = open(p).read()
old = '''        } else if (strcmp(argv[arg], "-sequential") == 0) {
            g_strategy = ICET_STRATEGY_SEQUENTIAL;'''
if '"-direct"' not in s:
    assert old in s, "SimpleTiming.c: the -sequential option was not found"
    s = s.replace(old, old + '''
        } else if (strcmp(argv[arg], "-direct") == 0) {
            g_strategy = ICET_STRATEGY_DIRECT;''')
    open(p, 'w').write(s)
EOF
  cmake -S "$OUT/icet-src" -B "$OUT/icet-build" -DCMAKE_BUILD_TYPE=Release \
    -DICET_USE_OPENGL=OFF -DICET_USE_OPENGL3=OFF -DICET_USE_MPI=ON -DBUILD_TESTING=ON >/dev/null
  make -C "$OUT/icet-build" -j2 icetTests_mpi >/dev/null
fi
ICET="$OUT/icet-build/bin/icetTests_mpi"
# This session's measurements only (the IceT build above is kept between sessions).
rm -f "$OUT/icet.csv" "$OUT"/strata-*.jsonl "$OUT/summary.md"

for r in $(seq 1 "$ROUNDS"); do
  for p in 2 4 8; do
    for dense in "" "-dense-images"; do
      for strat in "-sequential" "-sequential -bswap" "-direct"; do
        # shellcheck disable=SC2086
        mpirun --allow-run-as-root --oversubscribe -np "$p" "$ICET" -width 1920 -height 1080 \
          SimpleTiming -transparent $strat $dense -frames "$FRAMES" -seed 12345 \
          | grep '^LOG,' | sed "s/^/$r,$strat,/" >>"$OUT/icet.csv"
      done
    done
  done
  # Strata's sparse images at IceT's coverage: the active pixels one rank sent under
  # IceT's direct strategy this round (bytes sent over the p - 1 senders, 16 bytes a
  # pixel), as a fraction of the frame. IceT's boxes shrink as p grows; a fixed coverage
  # would compare different work.
  for p in 2 4 8; do
    cov=$(python3 - "$OUT/icet.csv" "$r" "$p" <<'EOF2'
import csv, statistics, sys
path, rnd, p = sys.argv[1], sys.argv[2], int(sys.argv[3])
b = [float(row[2:][-2]) for row in csv.reader(open(path))
     if row[0] == rnd and row[1] == "-direct" and int(row[2:][1]) == p
     and row[2:][12] == "no" and row[2:][14] != "0"]
print(f"{statistics.median(b) / (p - 1) / 16 / (1920 * 1080):.4f}")
EOF2
)
    echo "round $r: p = $p, sparse coverage $cov (IceT direct's active pixels per rank)"
    "$BENCH" --procs "$p" --transports shm --frames "$STRATA_FRAMES" --sparse-coverage "$cov" \
      --json "$OUT/strata-$r-p$p.jsonl" >/dev/null
  done
  echo "round $r done"
done

python3 - "$OUT" <<'EOF'
import csv, glob, json, statistics, sys
out = sys.argv[1]
# IceT: round,options,LOG,procs,multi-tile,single-image,...,dense images (col 13 of LOG),
# ..., frame (15), ..., frame time (last).
icet = {}
for row in csv.reader(open(f"{out}/icet.csv")):
    rnd, opts, rest = row[0], row[1], row[2:]
    p, dense, frame, t = int(rest[1]), rest[12] == "yes", int(rest[14]), float(rest[-1])
    if frame == 0:
        continue
    icet.setdefault((p, dense, opts, rnd), []).append(t * 1e3)
best_icet = {}
for (p, dense, opts, rnd), ts in icet.items():
    m = statistics.median(ts)
    k = (p, dense, opts)
    best_icet[k] = min(best_icet.get(k, m), m)
strata = {}
for f in glob.glob(f"{out}/strata-*.jsonl"):
    for line in open(f):
        v = json.loads(line)
        if v.get("transport") != "shm" or v.get("wire") != "f32":
            continue
        k = (v["procs"], v["density"] == "dense", v["algorithm"])
        strata[k] = min(strata.get(k, v["assembled_ms"]), v["assembled_ms"])
names = {"-sequential": "automatic (radix-kr)", "-sequential -bswap": "binary swap", "-direct": "direct"}
lines = ["| p | image | IceT automatic ms | IceT best ms (strategy) | Strata best ms (algorithm) | Strata / IceT automatic | Strata / IceT best |",
         "|---|---|---|---|---|---|---|"]
for p in (2, 4, 8):
    for dense in (True, False):
        auto = best_icet.get((p, dense, "-sequential"))
        ib = min(((t, o) for (q, d, o), t in best_icet.items() if q == p and d == dense), default=None)
        sb = min(((t, a) for (q, d, a), t in strata.items() if q == p and d == dense), default=None)
        if auto is None or ib is None or sb is None:
            continue
        lines.append(f"| {p} | {'dense' if dense else 'sparse'} | {auto:.1f} | {ib[0]:.1f} ({names[ib[1]]}) | "
                     f"{sb[0]:.1f} ({sb[1]}) | {sb[0] / auto:.2f} | {sb[0] / ib[0]:.2f} |")
detail = ["", "| p | image | IceT strategy | ms | | Strata algorithm | ms |", "|---|---|---|---|---|---|---|"]
for p in (2, 4, 8):
    for dense in (True, False):
        i = sorted((o, t) for (q, d, o), t in best_icet.items() if q == p and d == dense)
        s = sorted((a, t) for (q, d, a), t in strata.items() if q == p and d == dense)
        for j in range(max(len(i), len(s))):
            io = (names[i[j][0]], f"{i[j][1]:.1f}") if j < len(i) else ("", "")
            so = (s[j][0], f"{s[j][1]:.1f}") if j < len(s) else ("", "")
            detail.append(f"| {p} | {'dense' if dense else 'sparse'} | {io[0]} | {io[1]} | | {so[0]} | {so[1]} |")
open(f"{out}/summary.md", "w").write("\n".join(lines + detail) + "\n")
print("\n".join(lines + detail))
EOF
