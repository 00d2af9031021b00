#!/usr/bin/env bash
# The project's test command (README / CI): Rust build + unit tests, then the
# Python interop test against the release binary, then the Python bindings
# (built into the same target directory) and their pytest suite.
#
# Usage: bash scripts/test.sh
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

echo "== python environment"
bash scripts/setup-python.sh

echo "== cargo build --release -p brickyard"
cargo build --release -p brickyard

echo "== cargo test --workspace --release"
cargo test --workspace --release

echo "== interop"
bash scripts/interop/run.sh target/release/brickyard

echo "== python bindings"
bash scripts/python-bindings.sh
