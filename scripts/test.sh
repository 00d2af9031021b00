#!/usr/bin/env bash
# The project's test command (README / CI): Rust build + unit tests, then the
# Python interop test against the release binary, then the Python bindings
# (built into the same target directory) and their pytest suite.
#
# Usage: bash scripts/test.sh
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

# Background setup steps: each writes to its own log, which is shown when it
# is waited for (on failure to stderr, and the test run stops). Whatever
# is still running when this script ends is stopped with it.
trap 'kill $(jobs -p) 2>/dev/null || true' EXIT
await() { # NAME PID LOG
    echo "== $1"
    if ! wait "$2"; then
        cat "$3" >&2
        echo "$1 failed (log above)" >&2
        exit 1
    fi
    cat "$3"
}

# The Python environment (interop and bindings tests, at the end) is set up
# in the background while Cargo builds: the download and install of its
# packages is mostly waiting for the network and the disk.
SETUP_LOG="$(mktemp)"
echo "== python environment (in the background, log in $SETUP_LOG)"
bash scripts/setup-python.sh > "$SETUP_LOG" 2>&1 &
SETUP_PYTHON=$!

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

# The web client's tools (the wasm target, wasm-bindgen-cli from crates.io)
# are installed at a lower priority beside the native build: they take the
# cores that build leaves idle (its serial stretches and links).
TOOLS_LOG="$(mktemp)"
nice -n 10 bash scripts/build-web.sh --tools-only > "$TOOLS_LOG" 2>&1 &
WEB_TOOLS=$!

# One native build for everything: the workspace's tests, which also build
# the CLI (target/release/brickyard, used by the interop test below) and
# whose resolution of shared dependencies the Python bindings mirror
# (python/Cargo.toml). A separate `cargo build -p brickyard` would resolve
# features without the tests' dev-dependencies and compile zarrs, the
# window system crates and every brickyard crate twice.
echo "== cargo test --workspace --release --no-run ${FEATURES[*]}"
cargo test --workspace --release --no-run ${FEATURES[@]+"${FEATURES[@]}"}

# The web client (brickyard-web for wasm32, its glue and page in
# target/web/, the headless-browser test's driver): before the tests, whose
# browser test opens it in Chromium. Its wasm build is the check that the
# renderers, the device driver and the virtual memory build for the web.
await "web client tools" "$WEB_TOOLS" "$TOOLS_LOG"

echo "== web client"
bash scripts/build-web.sh

# Its data path, virtual memory and CPU renderer compiled to WebAssembly,
# tested in headless Chromium (wasm-bindgen-test-runner drives it through
# chromedriver; webdriver.json in the crate gives Chromium its flags).
echo "== web client tests in headless Chromium"
if command -v chromedriver >/dev/null 2>&1; then
    TD="${CARGO_TARGET_DIR:-target}"
    case "$TD" in /*) ;; *) TD="$PWD/$TD" ;; esac
    # The runner's default limit is 20 s for the whole run; a cold Chromium
    # (first start, empty shader cache, software WebGPU) on a busy 2-core
    # machine has been seen to take longer for the first WGSL compile.
    CARGO_TARGET_WASM32_UNKNOWN_UNKNOWN_RUNNER="$TD/tools/bin/wasm-bindgen-test-runner" \
        WASM_BINDGEN_TEST_TIMEOUT="${WASM_BINDGEN_TEST_TIMEOUT:-180}" \
        CHROMEDRIVER="$(command -v chromedriver)" \
        cargo test --release --target wasm32-unknown-unknown -p brickyard-web --test browser
elif [ "${BRICKYARD_SKIP_BROWSER:-}" = 1 ]; then
    echo "skipped: no chromedriver and BRICKYARD_SKIP_BROWSER=1"
else
    echo "chromedriver is missing (apt-get install chromium-driver); BRICKYARD_SKIP_BROWSER=1 opts out" >&2
    exit 1
fi

echo "== cargo test --workspace --release ${FEATURES[*]}"
cargo test --workspace --release ${FEATURES[@]+"${FEATURES[@]}"}

await "python environment" "$SETUP_PYTHON" "$SETUP_LOG"

echo "== interop"
bash scripts/interop/run.sh target/release/brickyard

echo "== python bindings"
bash scripts/python-bindings.sh
