#!/usr/bin/env bash
# Builds, lints and runs the freestanding firmware binary, then prints its section sizes.
# For CI (x86-64 Linux): `bash firmware-demo/freestanding.sh`. Exits non-zero if the
# binary does not build, clippy complains, or any of the binary's checks fails.
set -euo pipefail
cd "$(dirname "$0")/.."

features=(-p firmware-demo --bin firmware-freestanding --no-default-features --features freestanding)
cargo clippy "${features[@]}" --profile firmware -- -D warnings
cargo build "${features[@]}" --profile firmware
binary=target/firmware/firmware-freestanding
"$binary"
# .text is code, .rodata holds the embedded weights and frames, .bss the arena.
size -A "$binary" | awk '$1 ~ /^\.(text|rodata|data|bss)/ { printf "%-14s %9d bytes\n", $1, $2 }'
