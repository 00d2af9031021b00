#!/usr/bin/env bash
# Run every fuzz target of fuzz/ for a set time and print a report: target,
# seconds, executions, crashes found. Needs a nightly toolchain and
# cargo-fuzz (`cargo install cargo-fuzz`); not part of CI (the regression
# tests of every crash found run as normal tests). See docs/FUZZING.md.
#
# Usage: bash scripts/fuzz.sh [SECONDS_PER_TARGET]     (default 60)
# Env:   FUZZ_TARGETS="nrrd_header tiff_header"  to run some targets only
#        FUZZ_ARGS="-rss_limit_mb=4096"           extra libFuzzer flags
#
# Each target starts from its seeds (fuzz/seeds/TARGET, read only) and its
# growing corpus (fuzz/corpus/TARGET); crashing inputs land in
# fuzz/artifacts/TARGET and logs in fuzz/logs. A run stops at its first
# crash; the report counts the crash, timeout and out-of-memory inputs it
# left.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
ROOT="$PWD"

SECS="${1:-60}"
ALL="nrrd_header nifti_header tiff_header raw_sidecar omezarr_meta zarr_array shard_index"
read -r -a TARGETS <<<"${FUZZ_TARGETS:-$ALL}"

if ! cargo +nightly fuzz --version >/dev/null 2>&1; then
    echo "fuzz.sh: needs cargo-fuzz on a nightly toolchain: rustup toolchain install nightly; cargo install cargo-fuzz" >&2
    exit 2
fi

echo "== cargo +nightly fuzz build (${TARGETS[*]})"
for t in "${TARGETS[@]}"; do
    cargo +nightly fuzz build --fuzz-dir "$ROOT/fuzz" "$t"
done

mkdir -p fuzz/logs
report=()
for t in "${TARGETS[@]}"; do
    corpus="$ROOT/fuzz/corpus/$t"
    artifacts="$ROOT/fuzz/artifacts/$t"
    logdir="$ROOT/fuzz/logs/$t"
    mkdir -p "$corpus" "$artifacts" "$logdir"
    before=$(find "$artifacts" -type f \( -name 'crash-*' -o -name 'oom-*' -o -name 'timeout-*' -o -name 'leak-*' \) | wc -l)
    echo "== $t: ${SECS}s"
    start=$(date +%s)
    # -jobs=1: one fuzzing process, its output in $logdir/fuzz-0.log.
    # shellcheck disable=SC2086
    (cd "$logdir" && cargo +nightly fuzz run --fuzz-dir "$ROOT/fuzz" "$t" "$corpus" "$ROOT/fuzz/seeds/$t" -- \
        -max_total_time="$SECS" -jobs=1 -timeout=20 ${FUZZ_ARGS:-}) \
        >"$logdir/run.log" 2>&1 || true
    took=$(($(date +%s) - start))
    log="$logdir/fuzz-0.log"
    [ -f "$log" ] || log="$logdir/run.log"
    # Executions: libFuzzer's "Done N runs" line, else its last "#N" status line.
    execs=$(grep -oE 'Done [0-9]+ runs' "$log" | tail -1 | grep -oE '[0-9]+' || true)
    if [ -z "$execs" ]; then
        execs=$(grep -oE '^#[0-9]+' "$log" | tail -1 | tr -d '#' || true)
    fi
    after=$(find "$artifacts" -type f \( -name 'crash-*' -o -name 'oom-*' -o -name 'timeout-*' -o -name 'leak-*' \) | wc -l)
    crashes=$((after - before))
    report+=("$(printf '%-14s %8s %14s %8s' "$t" "$took" "${execs:-?}" "$crashes")")
    if [ "$crashes" -gt 0 ]; then
        echo "   $crashes new crashing input(s) in $artifacts (log: $log)"
    fi
done

echo
echo "== fuzz report ($(date -u +%Y-%m-%d), ${SECS}s per target)"
printf '%-14s %8s %14s %8s\n' target seconds executions crashes
total=0
for line in "${report[@]}"; do
    echo "$line"
    n=$(echo "$line" | awk '{print $3}')
    [[ "$n" =~ ^[0-9]+$ ]] && total=$((total + n))
done
echo "total executions: $total"
