#!/usr/bin/env bash
# Local: the two re-split models side by side, interleaved rounds.
set -euo pipefail
cd "$(dirname "$0")/.."
ROUNDS="${ROUNDS:-2}"
for r in $(seq 1 "$ROUNDS"); do
  for m in pages leaves; do
    echo "== round $r model $m"
    PS="${PS:-2}" MODES="${MODES:-off}" FRAMES="${FRAMES:-12}" THREADS="${THREADS:-1}" \
      COORDINATOR=./target/release/coordinator OUT="/tmp/models/r${r}_$m" \
      bash bench/strong-scaling.sh configs/demo.toml --set volume.0.opacity=0.06 \
      --set render.backend=cpu --set cluster.rebalance_model=$m "$@" 2>&1 | grep "^|.* ms |"
  done
done
