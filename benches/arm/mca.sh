#!/usr/bin/env bash
# llvm-mca cycles per iteration of the aarch64 kernels' hot loops (docs/ARM.md, the table
# in benches/README.md). Needs the cross toolchain of docs/ARM.md and Debian's llvm-19.
# `bash benches/arm/mca.sh`
set -euo pipefail
cd "$(dirname "$0")/../.."
export RUSTC=/usr/bin/rustc RUSTDOC=/usr/bin/rustdoc CARGO_TARGET_DIR=target/aarch64
export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER=aarch64-linux-gnu-gcc
export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_RUSTFLAGS="-C target-feature=+crt-static"
/usr/bin/cargo build -q --release --target aarch64-unknown-linux-gnu -p scdp-tests --bin simd-bits
work=$(mktemp -d)
aarch64-linux-gnu-objdump -d --no-show-raw-insn \
  target/aarch64/aarch64-unknown-linux-gnu/release/simd-bits >"$work/all.s"
# name | function (substring of its symbol) | mnemonic counted
loops=(
  "trunk digits (dot)|aarch644int83dot4conv|sdot"
  "trunk bytes centred (dot)|aarch645bytes18checked_conv_bytes|sdot"
  "trunk bytes (i8mm)|mmla18checked_conv_bytes|usmmla"
  "trunk bytes, pair layout (i8mm)|mmla17paired_conv_bytes|usmmla"
  "U-Net signed narrow codes (dot)|backends25checked_conv_signed_bytes|sdot"
  "U-Net signed narrow codes (i8mm)|mmla25checked_conv_signed_bytes|smmla"
  "U-Net signed narrow codes, pair layout (i8mm)|mmla24paired_conv_signed_bytes|smmla"
  "FiLM rows (dot, i8mm)|aarch646matvec12matvec_codes|sdot"
  "U-Net 15-bit codes (all)|aarch644int83dot10conv_codes|smull"
  "trunk digits (neon)|aarch644int84neon4conv|smull"
  "f32 2-D tile|backends8conv_f32|fmla"
  "f32 U-Net stream|sequence4neon12convolve_f32|fmla"
)
printf "| loop | instructions | %s |\n|---|---:|---:|---:|---:|\n" "neoverse-n1 | cortex-a76 (A57 model) | neoverse-v2"
for entry in "${loops[@]}"; do
  IFS='|' read -r name function mnemonic <<<"$entry"
  python3 benches/arm/innermost_loop.py "$work/all.s" "$function" "$mnemonic" >"$work/loop.s"
  counts=$(grep -oE "^(sdot|usdot|usmmla|smmla|smull2?|fmla)\b" "$work/loop.s" | sort | uniq -c | awk '{ printf "%s%d %s", sep, $1, $2; sep=", " }')
  cycles=()
  for cpu in neoverse-n1 cortex-a76 neoverse-v2; do
    cycles+=("$(llvm-mca-19 -mtriple=aarch64 -mcpu=$cpu -mattr=+dotprod,+i8mm -iterations=2000 "$work/loop.s" |
      awk '/Total Cycles/ { printf "%.1f", $3 / 2000 }')")
  done
  printf "| %s | %s | %s | %s | %s |\n" "$name" "$counts" "${cycles[@]}"
done
rm -r "$work"
