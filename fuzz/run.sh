#!/usr/bin/env bash
# Coverage-guided fuzzing of Strata's untrusted inputs with AFL++ (cargo-afl), then the
# corpus minimised back into fuzz/corpus/<target>/. Not run by CI (CI replays the corpus:
# tests/tests/fuzz_corpus.rs). Usage:
#   fuzz/run.sh [EXECS] [TARGET...]      # default 1000000 executions, every target
# Needs: cargo install cargo-afl && cargo afl config --build (once).
set -euo pipefail
cd "$(dirname "$0")"
EXECS=${1:-1000000}
shift || true
TARGETS=("$@")
if [ ${#TARGETS[@]} -eq 0 ]; then
  TARGETS=(segy horizon_text store store_sealed wire_header wire_message sparse_piece scene_toml)
fi
cargo afl build --release
BIN=target/release/strata-fuzz
OUT=${STRATA_FUZZ_OUT:-/tmp/strata-afl}
mkdir -p "$OUT"
# The sandbox's core_pattern and CPU governor are not ours to change.
export AFL_SKIP_CPUFREQ=1 AFL_I_DONT_CARE_ABOUT_MISSING_CRASHES=1 AFL_NO_UI=1
export AFL_NO_AFFINITY=1 AFL_SKIP_CRASHES=1
# afl-cmin.bash: the Python afl-cmin of this AFL++ finds no tuples with a persistent-mode
# Rust target and would leave an empty corpus.
AFL_BIN=$(dirname "$(ls -d "$HOME"/.local/share/afl.rs/rustc-*/afl.rs-*/afl/bin/afl-fuzz | tail -1)")
minimise() {
  local t=$1
  rm -rf "$OUT/$t.min"
  PATH="$AFL_BIN:$PATH" AFL_PATH="$AFL_BIN" "$AFL_BIN/afl-cmin.bash" \
    -i "$OUT/$t/default/queue" -o "$OUT/$t.min" -t 2000 -- "$BIN" "$t" > "$OUT/$t.cmin.log" 2>&1 || true
  # Keep what covers distinct edges; replace the old corpus only with a non-empty result.
  if [ -n "$(ls -A "$OUT/$t.min" 2>/dev/null)" ]; then
    rm -rf "corpus/$t" && mv "$OUT/$t.min" "corpus/$t"
    echo "  corpus/$t: $(ls "corpus/$t" | wc -l) inputs"
  else
    echo "  minimisation failed (see $OUT/$t.cmin.log); corpus/$t kept" >&2
  fi
}
if [ "${MINIMISE_ONLY:-0}" = 1 ]; then
  for t in "${TARGETS[@]}"; do minimise "$t"; done
  exit 0
fi
for t in "${TARGETS[@]}"; do
  start=$(date +%s)
  # -E: stop after EXECS executions; -t: 2 s per input (a hang is a finding too).
  cargo afl fuzz -i "corpus/$t" -o "$OUT/$t" -E "$EXECS" -t 2000 -- "$BIN" "$t" \
    > "$OUT/$t.log" 2>&1 || true
  end=$(date +%s)
  stats="$OUT/$t/default/fuzzer_stats"
  execs=$(awk -F' *: *' '$1=="execs_done"{print $2}' "$stats")
  crashes=$(awk -F' *: *' '$1=="saved_crashes"{print $2}' "$stats")
  hangs=$(awk -F' *: *' '$1=="saved_hangs"{print $2}' "$stats")
  edges=$(awk -F' *: *' '$1=="edges_found"{print $2}' "$stats")
  paths=$(awk -F' *: *' '$1=="corpus_count"{print $2}' "$stats")
  echo "$t: $execs executions in $((end - start)) s, $crashes crashes, $hangs hangs, $edges edges, $paths queue entries"
  minimise "$t"
  if [ "${crashes:-0}" != 0 ]; then
    echo "  crashes in $OUT/$t/default/crashes" >&2
  fi
done
