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

# MPI (`mpirun -n N brickyard …`, the `mpi` feature) where the system has
# it (OpenMPI: libopenmpi-dev, openmpi-bin; libclang for the binding's
# bindgen). The build and the tests take the same features, so that
# nothing is compiled twice. BRICKYARD_REQUIRE_MPI=1 (CI) makes a missing
# MPI a failure rather than a build without it.
FEATURES=()
if command -v mpicc >/dev/null 2>&1 && command -v mpirun >/dev/null 2>&1; then
    FEATURES=(--features brickyard/mpi)
elif [ "${BRICKYARD_REQUIRE_MPI:-}" = 1 ]; then
    echo "BRICKYARD_REQUIRE_MPI=1 but MPI is missing (mpicc, mpirun: install libopenmpi-dev openmpi-bin)" >&2
    exit 1
fi

echo "== cargo build --release -p brickyard ${FEATURES[*]}"
cargo build --release -p brickyard ${FEATURES[@]+"${FEATURES[@]}"}

echo "== cargo test --workspace --release ${FEATURES[*]}"
cargo test --workspace --release ${FEATURES[@]+"${FEATURES[@]}"}

echo "== interop"
bash scripts/interop/run.sh target/release/brickyard

# The browser's side: the renderers, the device driver, the residency
# octree and the virtual memory build for wasm32-unknown-unknown (WebGPU),
# without the loader's threads and files. A build check: they run in
# the browser only once the web client exists.
echo "== wasm32 build (brickyard-render without the loader)"
if command -v rustup >/dev/null 2>&1; then
    rustup target add wasm32-unknown-unknown >/dev/null
fi
cargo build --release --target wasm32-unknown-unknown -p brickyard-render --no-default-features

echo "== python bindings"
bash scripts/python-bindings.sh
