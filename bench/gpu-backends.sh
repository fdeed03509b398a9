#!/usr/bin/env bash
# The engine's CPU and GPU backends on the same frames (bonsai, ParaView's setup, 1920×1080
# and 3840×2160): cold batch, converged frame, samples/s, bytes uploaded, feedback bytes read
# back per frame, and the GPU image's largest difference from the CPU image.
#
# Here (no GPU) wgpu runs on Mesa's lavapipe. On a GPU node without a Rust toolchain: build
# here (`cargo build --release -p strata-bench`), copy target/release/bench-render and the
# bonsai raw file next to each other, then run `bench-render --only-backends --bonsai FILE`.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release -p strata-bench --bin bench-render
./target/release/bench-render --only-backends --frames "${FRAMES:-3}" "$@"
