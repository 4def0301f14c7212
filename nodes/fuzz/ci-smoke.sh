#!/usr/bin/env bash
# A bounded fuzz run for CI: every target in nodes/fuzz/fuzz_targets for N seconds
# each (default 20), from the seed corpus generated from the test vectors (nodes/tests/vectors).
# Fails on the first crash (libFuzzer leaves the input in fuzz/artifacts/TARGET/).
# Usage: nodes/fuzz/ci-smoke.sh [SECONDS]    (honours CARGO_TARGET_DIR)
set -euo pipefail
seconds=${1:-20}
here=$(cd "$(dirname "$0")" && pwd)

if ! command -v cargo-fuzz >/dev/null 2>&1; then
  cargo install cargo-fuzz --version 0.13.2
fi
"$here/seed_corpus.sh"
"$here/seed_corpus_modbus.sh"

# cargo-fuzz passes `-Z` flags to rustc; on a stable toolchain that needs bootstrap mode.
export RUSTC_BOOTSTRAP=1
cd "$here/.."
for source in "$here"/fuzz_targets/*.rs; do
  target=$(basename "$source" .rs)
  echo "== fuzz $target for ${seconds}s"
  cargo fuzz run "$target" "fuzz/corpus/$target" -- -max_total_time="$seconds"
done
