#!/usr/bin/env bash
# A fuzzing campaign by hand (CI runs ci-smoke.sh instead): every target in
# nodes/fuzz/fuzz_targets for SECONDS each (default 600), one after another,
# from the seed corpus plus whatever earlier campaigns found. Prints, per
# target, the executions and libFuzzer's final coverage (cov) and feature (ft)
# counts; the whole libFuzzer output is in fuzz/logs/TARGET.log. A crash stops
# the campaign with its input left in fuzz/artifacts/TARGET/: add it to the
# target's regression test before fixing it.
# Usage: nodes/fuzz/campaign.sh [SECONDS]    (honours CARGO_TARGET_DIR)
set -euo pipefail
seconds=${1:-600}
here=$(cd "$(dirname "$0")" && pwd)

if ! command -v cargo-fuzz >/dev/null 2>&1; then
  cargo install cargo-fuzz --version 0.13.2
fi
"$here/seed_corpus.sh"
"$here/seed_corpus_modbus.sh"

export RUSTC_BOOTSTRAP=1
cd "$here/.."
mkdir -p fuzz/logs
printf '%-16s %12s %8s %8s %8s\n' target executions cov ft corpus
for source in "$here"/fuzz_targets/*.rs; do
  target=$(basename "$source" .rs)
  log=fuzz/logs/$target.log
  cargo fuzz build "$target" >"$log" 2>&1
  cargo fuzz run "$target" "fuzz/corpus/$target" -- \
    -max_total_time="$seconds" -print_final_stats=1 >>"$log" 2>&1
  # libFuzzer's last status line: "#N DONE cov: C ft: F corp: K/..."
  last=$(grep -E '^#[0-9]+' "$log" | tail -1)
  runs=$(sed -nE 's/^stat::number_of_executed_units: *([0-9]+).*/\1/p' "$log" | tail -1)
  cov=$(sed -nE 's/.* cov: ([0-9]+).*/\1/p' <<<"$last")
  ft=$(sed -nE 's/.* ft: ([0-9]+).*/\1/p' <<<"$last")
  corp=$(sed -nE 's/.* corp: ([0-9]+).*/\1/p' <<<"$last")
  printf '%-16s %12s %8s %8s %8s\n' "$target" "$runs" "$cov" "$ft" "$corp"
done
