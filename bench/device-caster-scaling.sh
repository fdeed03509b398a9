#!/usr/bin/env bash
# Issue 14's thread scaling, prepared for the `device` machine (16 cores, no Rust toolchain,
# no ../shared): the CPU caster on the bonsai at 1024² and 1920×1080 on 1, 2, 4, 8 and 16
# threads, each a separate rayon pool, the default path next to the 8-lane packets and the
# plain scalar march, in one run.
#
# Prepare on the project machine, once per build:
#   grep -qx '/device-carry/' .git/info/exclude || echo /device-carry/ >> .git/info/exclude
#   cargo build --release --locked -p strata-bench
#   mkdir -p device-carry && cp target/release/bench-render device-carry/ &&
#     strip device-carry/bench-render &&
#     cp ../shared/data/real/volumes/bonsai/bonsai_256x256x256_uint8.raw device-carry/
# Run there with the device tool: carry ["device-carry"], command
#   bash bench/device-caster-scaling.sh device-carry "$OUT"
# (about 3 minutes on 16 cores; the table lands in $OUT/caster-scaling.md).
# Usage: bench/device-caster-scaling.sh CARRY_DIR OUT_DIR [THREADS, default 1,2,4,8,16]
set -euo pipefail
CARRY=${1:?folder with bench-render and the bonsai raw file}
OUT=${2:?output folder}
THREADS=${3:-1,2,4,8,16}
FRAMES=${FRAMES:-5}
mkdir -p "$OUT"
{
  echo "# CPU caster thread scaling ($(nproc) cores: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs))"
  echo
  echo "\`bench-render --only-caster --case Bonsai --threads $THREADS --frames $FRAMES\`"
  echo
  "$CARRY/bench-render" --only-caster --case Bonsai --threads "$THREADS" --frames "$FRAMES" \
    --path-filter "" --bonsai "$CARRY/bonsai_256x256x256_uint8.raw" --dir "${TMPDIR:-/tmp}/strata-bench"
} 2>&1 | tee "$OUT/caster-scaling.md"
