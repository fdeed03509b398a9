#!/usr/bin/env bash
# Builds and packs what bench/device-all.sh needs on the `device` machine (no Rust toolchain
# and no ../shared there): stripped, gzipped release binaries (bench-render, coordinator),
# the GPU test binaries (test profile: render_gpu, hard_cases), GNU time and the bonsai raw file in device-carry/, and
# the Vulkan loader's packages in .gl/ (/work/.library/device/README.md). Both folders are
# added to .git/info/exclude. About 18 MB; then call the device tool with
#   carry [".gl", "device-carry"], command `bash bench/device-all.sh "$OUT"`.
#
# Usage: bench/device-prepare.sh   (from anywhere in the checkout)
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p .git/info
for d in /.gl/ /device-carry/; do
  grep -qxF "$d" .git/info/exclude 2>/dev/null || echo "$d" >>.git/info/exclude
done
if ! ls .gl/libvulkan1_*.deb >/dev/null 2>&1; then
  mkdir -p .gl /tmp/amd64/partial
  o=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
  apt-get "${o[@]}" update -qq
  (cd .gl && apt-get "${o[@]}" download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
fi
cargo build --release --locked -p strata-bench -p strata-coordinator
test_exe() { # the executable of test target $1 (test profile)
  cargo test --locked -p strata-tests --test "$1" --no-run --message-format=json 2>/dev/null |
    python3 -c 'import json,sys
for l in sys.stdin:
    m = json.loads(l)
    if m.get("reason") == "compiler-artifact" and m.get("executable") and m["target"]["name"] == sys.argv[1]:
        print(m["executable"])' "$1"
}
gpu_test=$(test_exe render_gpu)
[ -x "$gpu_test" ] || { echo "error: no render_gpu test binary was built" >&2; exit 1; }
hard_cases=$(test_exe hard_cases)
[ -x "$hard_cases" ] || { echo "error: no hard_cases test binary was built" >&2; exit 1; }
bonsai=../shared/data/real/volumes/bonsai/bonsai_256x256x256_uint8.raw
[ -f "$bonsai" ] || { echo "error: $bonsai is missing (../shared beside the checkout)" >&2; exit 1; }
rm -rf device-carry
mkdir device-carry
strip -o device-carry/bench-render target/release/bench-render
strip -o device-carry/coordinator target/release/coordinator
strip -o device-carry/render_gpu "$gpu_test"
strip -o device-carry/hard_cases "$hard_cases"
cp /usr/bin/time "$bonsai" device-carry/
gzip -6 device-carry/*
du -sh device-carry .gl
