#!/usr/bin/env bash
# The edge fit on aarch64 (docs/architecture.md): `cargo check` of the crate, its tests and
# the binary for aarch64-unknown-linux-gnu, then the kernel's tests (the NEON copy against
# the baseline, bit for bit, src/geom/kernel.rs) run on an emulated aarch64 CPU: the kernel
# module and its test generator compiled alone (they need only glam) in a scratch crate
# under the target folder, linked with aarch64-linux-gnu-gcc, run by qemu-aarch64.
#
# Needs: rustup target add aarch64-unknown-linux-gnu; for the run,
# apt-get install qemu-user gcc-aarch64-linux-gnu libc6-dev-arm64-cross (without them
# only the check runs, and the script says so).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
target=aarch64-unknown-linux-gnu
cargo check --release --locked --target "$target" -p linegs-gpu --lib --bins --tests
echo "test-aarch64: cargo check --target $target passed"

if ! command -v qemu-aarch64 >/dev/null 2>&1 || ! command -v aarch64-linux-gnu-gcc >/dev/null 2>&1; then
  echo "test-aarch64: no qemu-aarch64 or aarch64-linux-gnu-gcc: the kernel's tests did not run" \
    "(apt-get install qemu-user gcc-aarch64-linux-gnu libc6-dev-arm64-cross)"
  exit 0
fi
dir=${CARGO_TARGET_DIR:-$root/target}/aarch64-kernel
mkdir -p "$dir/src"
cat >"$dir/Cargo.toml" <<TOML
[package]
name = "aarch64-kernel"
version = "0.1.0"
edition = "2021"
publish = false

[dependencies]
glam = "0.30"

[workspace]
TOML
cat >"$dir/src/lib.rs" <<RS
//! linegs-gpu's src/geom/kernel.rs alone, with the generator its tests use.
pub mod geom {
    #[path = "$root/src/geom/kernel.rs"]
    pub mod kernel;
}
pub mod synth {
    #[path = "$root/src/synth/rng.rs"]
    mod rng;
    pub use rng::Rng;
}
RS
# the project's versions (glam's)
cp "$root/Cargo.lock" "$dir/Cargo.lock"
export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER=aarch64-linux-gnu-gcc
export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_RUNNER="qemu-aarch64 -L /usr/aarch64-linux-gnu"
out=$(CARGO_TARGET_DIR="$dir/target" cargo test --release --manifest-path "$dir/Cargo.toml" \
  --target "$target" geom::kernel 2>&1) || { echo "$out"; exit 1; }
echo "$out" | grep -E '^test |test result'
# the NEON copy ran: the vector test is there and passed
echo "$out" | grep -q 'the_vector_copy_is_the_baseline_to_the_bit_from_near_to_underflow ... ok' ||
  { echo "test-aarch64: the kernel's vector test did not run" >&2; exit 1; }
echo "test-aarch64: ok (the NEON kernel gives the baseline's bits under qemu-aarch64)"
