#!/usr/bin/env bash
# Issue 14's comparison in one run, one after the other on an idle machine:
#   1. the CPU caster as of commit c8b4383 (before issue 14), through that commit's
#      bench-render with bench/baseline-c8b4383.patch applied (STRATA_BASELINE=1: bonsai
#      1024² and 1920×1080, demo at volume opacity 0 and 0.06, 1 and 2 threads);
#   2. today's caster, every path (bench-render --only-caster);
#   3. ParaView 5.11 on the bonsai at 1024² ('Ray Cast Only' and 'Smart'), when pvbatch is
#      installed (Debian: apt-get install paraview python3-paraview xvfb openmpi-bin).
# Usage: bench/caster-side-by-side.sh BEFORE_BENCH_RENDER [OUTDIR]
# Build BEFORE_BENCH_RENDER with:
#   git worktree add /tmp/before c8b4383 && cd /tmp/before &&
#   git apply "$OLDPWD/bench/baseline-c8b4383.patch" &&
#   ln -s "$OLDPWD/configs/synthetic" configs/synthetic &&
#   CARGO_TARGET_DIR=/tmp/before-target cargo build --release -p strata-bench
set -euo pipefail
BEFORE=${1:?path to the baseline bench-render}
OUT=${2:-/tmp/strata-caster-side-by-side}
HERE=$(cd "$(dirname "$0")/.." && pwd)
FRAMES=${FRAMES:-3}
mkdir -p "$OUT"
cd "$HERE"
cargo build --release -p strata-bench
echo "## 1. before (c8b4383)"
STRATA_BASELINE=1 "$BEFORE" --frames "$FRAMES" | tee "$OUT/before.md"
echo "## 2. now"
./target/release/bench-render --only-caster --frames "$FRAMES" | tee "$OUT/now.md"
if command -v pvbatch >/dev/null; then
  echo "## 3. ParaView"
  ONLY="np1_raycastonly_1024 np1_smart_1024" \
    ../shared/baselines/run_paraview_matrix.sh \
    ../shared/data/real/volumes/bonsai/bonsai_256x256x256_uint8.raw "$OUT/paraview" 256 256 256 uint8 10
else
  echo "pvbatch not found: ParaView not run"
fi
