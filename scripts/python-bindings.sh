#!/usr/bin/env bash
# Build the Python bindings (python/) with maturin into the workspace's target
# directory, where `cargo build --release` has already built the crates they
# use, install the wheel into the repo venv and run their pytest suite
# against the release binary.
#
# Usage: bash scripts/python-bindings.sh        (after scripts/setup-python.sh
#        and cargo build --release -p brickyard)
# Env:   CARGO_TARGET_DIR (default: target/)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$ROOT/target}"
PY="$ROOT/.venv/bin/python"
BIN="$CARGO_TARGET_DIR/release/brickyard"
[ -x "$BIN" ] || { echo "python-bindings: $BIN not built" >&2; exit 1; }

t0=$(date +%s)
rm -rf "$CARGO_TARGET_DIR/wheels/brickyard-"*.whl
"$ROOT/.venv/bin/maturin" build --release --quiet -m python/Cargo.toml -o "$CARGO_TARGET_DIR/wheels"
"$PY" -m pip install --quiet --disable-pip-version-check --force-reinstall --no-deps \
    "$CARGO_TARGET_DIR/wheels/"brickyard-*.whl
t1=$(date +%s)
echo "python-bindings: wheel built and installed in $((t1 - t0)) s"
# From outside python/, so that the installed package is what is tested.
cd "$ROOT/python/tests"
BRICKYARD_BIN="$BIN" "$PY" -m pytest -q -p no:cacheprovider .
echo "python-bindings: tests took $(( $(date +%s) - t1 )) s"
