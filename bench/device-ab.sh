#!/usr/bin/env bash
# Two coordinator builds side by side on the `device` machine: the demo orbit
# (bench/strong-scaling.sh, volume opacity 0.06, CPU backend, 2 threads per worker) at each p
# of PS with both builds, interleaved over ROUNDS rounds, so that the machine's drift and
# noise fall on both alike, each round starting with p = 1 of the second build (the
# efficiency's baseline). Prints one table row per run (the script's two tables) and writes them to
# $RESULTS/ab.md.
#
#   bench/device-ab.sh RESULTS OLD_COORDINATOR NEW_COORDINATOR
#
# Environment: PS ("8"), MODES ("on"), ROUNDS (3), FRAMES (12), CARRY (device-carry, which
# holds GNU time). Prepare with bench/device-prepare.sh, then put the other build, stripped
# and gzipped, in device-carry too (e.g. coordinator-old.gz); the script unpacks every *.gz
# in CARRY. docs/BENCHMARKS.md ("On an H100 machine") has a run.
set -uo pipefail
cd "$(dirname "$0")/.."
RESULTS=${1:?results folder}
OLD=${2:?old coordinator}
NEW=${3:?new coordinator}
CARRY=${CARRY:-device-carry}
PS=${PS:-8}
MODES=${MODES:-on}
ROUNDS=${ROUNDS:-3}
FRAMES=${FRAMES:-12}
mkdir -p "$RESULTS"
for f in "$CARRY"/*.gz; do [ -e "$f" ] && gunzip -f "$f"; done
chmod +x "$OLD" "$NEW" "$CARRY"/time 2>/dev/null
run() { # LABEL BUILD PS MODES
  echo "## $1, p = $3, occlusion $4"
  PS="$3" MODES="$4" FRAMES=$FRAMES COORDINATOR="$2" TIME_BIN="$CARRY/time" \
    OUT="/tmp/device-ab/$1" bash bench/strong-scaling.sh configs/demo.toml \
    --set volume.0.opacity=0.06 --set render.backend=cpu 2>&1 | grep "^|"
}
{
  for r in $(seq 1 "$ROUNDS"); do
    echo "# round $r"
    run "new-p1-$r" "$NEW" 1 "$MODES"
    for p in $PS; do
      run "old-$p-$r" "$OLD" "$p" "$MODES"
      run "new-$p-$r" "$NEW" "$p" "$MODES"
    done
  done
} | tee "$RESULTS/ab.md"
tar czf "$RESULTS/ab-raw.tgz" -C /tmp --exclude '*.png' device-ab 2>/dev/null
