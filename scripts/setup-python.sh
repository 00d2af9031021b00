#!/usr/bin/env bash
# Create (if missing) the repo-local Python virtualenv `.venv` and install the
# interop test requirements into it. Idempotent: when the venv exists and the
# requirements file has not changed since the last successful install, it
# returns immediately.
#
# Usage: bash scripts/setup-python.sh        (from anywhere)
# Env:   PYTHON=python3.11 to choose the interpreter (default: python3)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
REQ="$ROOT/scripts/interop/requirements.txt"
STAMP="$VENV/.interop-requirements.sha256"
PY="${PYTHON:-python3}"

if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c 'import sys' >/dev/null 2>&1; then
    echo "setup-python: creating $VENV with $($PY --version 2>&1)"
    rm -rf "$VENV"
    "$PY" -m venv "$VENV"
fi

want="$(sha256sum "$REQ" | cut -d' ' -f1)"
have="$(cat "$STAMP" 2>/dev/null || true)"
if [ "$want" = "$have" ]; then
    echo "setup-python: $VENV up to date"
    exit 0
fi

echo "setup-python: installing $(basename "$REQ") into $VENV"
"$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -r "$REQ"
"$VENV/bin/python" -c 'import numpy, zarr, numcodecs, ome_zarr; print("setup-python: numpy", numpy.__version__, "zarr", zarr.__version__, "numcodecs", numcodecs.__version__, "ome-zarr", ome_zarr.__version__)'
echo "$want" > "$STAMP"
