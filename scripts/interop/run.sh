#!/usr/bin/env bash
# Interop test: brickyard output checked with zarr-python / numpy / ome-zarr-py,
# Python-written stores (ome-zarr-py, zarr-python v2/v3) converted by brickyard,
# NIfTI rescaling (scl_slope/scl_inter) compared with nibabel,
# `brickyard process` compared with scipy.ndimage, and s3:// stores read
# from moto's S3 server.
#
# Usage: bash scripts/interop/run.sh BRICKYARD_BIN
# Env:   INTEROP_KEEP=1     keep the temp dir (always kept on failure)
#        INTEROP_ONLY=regex run only cases whose name matches
#        PYTHON=...         interpreter (default: .venv/bin/python, else python3)
#
# Ends with the line "interop: N passed, M failed"; exit status 1 if M > 0.
set -uo pipefail

if [ $# -ne 1 ]; then
    echo "usage: $0 BRICKYARD_BIN" >&2
    exit 2
fi
BIN="$(realpath "$1")"
if [ ! -x "$BIN" ]; then
    echo "interop: brickyard binary $1 not found or not executable" >&2
    echo "interop: 0 passed, 1 failed"
    exit 1
fi
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
ROOT="$(cd "$HERE/../.." && pwd)"
if [ -n "${PYTHON:-}" ]; then PY="$PYTHON"
elif [ -x "$ROOT/.venv/bin/python" ]; then PY="$ROOT/.venv/bin/python"
else PY=python3; fi
TMP="$(mktemp -d -t brickyard-interop.XXXXXX)"
mkdir -p "$TMP/logs"
CMD_TIMEOUT="${INTEROP_TIMEOUT:-600}"
echo "interop: brickyard=$BIN python=$PY tmp=$TMP"

# ---------------------------------------------------------------- helpers
by()    { echo "+ brickyard $*" >&2; timeout "$CMD_TIMEOUT" "$BIN" "$@"; }
py()    { echo "+ python $*" >&2; timeout "$CMD_TIMEOUT" "$PY" "$@"; }
check() { py "$HERE/check_output.py" "$@"; }

# sidecar of a generated/raw file: brief says OUTPUT.json; accept both spellings
sidecar_of() {
    if [ -f "$1.json" ]; then echo "$1.json"
    elif [ -f "${1%.*}.json" ]; then echo "${1%.*}.json"
    else echo "no sidecar for $1 (looked for $1.json and ${1%.*}.json)" >&2; return 1; fi
}

passed=0; failed=0; failed_names=()
run_case() {
    local name="$1"; shift
    if [ -n "${INTEROP_ONLY:-}" ] && ! [[ "$name" =~ $INTEROP_ONLY ]]; then return 0; fi
    local log="$TMP/logs/$name.log" t0=$SECONDS rc
    # errexit inside the subshell; not a conditional context, so -e stays active
    ( set -e; "$@" ) >"$log" 2>&1
    rc=$?
    if [ $rc -eq 0 ]; then
        passed=$((passed + 1))
        printf 'interop: PASS %-28s (%ds)\n' "$name" $((SECONDS - t0))
    else
        failed=$((failed + 1)); failed_names+=("$name")
        printf 'interop: FAIL %-28s (%ds, rc=%d, log %s)\n' "$name" $((SECONDS - t0)) $rc "$log"
        # the concrete problems (from the checkers' summaries) or the end of the log
        if grep -q '^  - ' "$log"; then
            sed -n '/^[a-z_]*: FAILED/,$p' "$log" | head -n 60 | sed 's/^/    | /'
        else
            grep -E '^\s*FAIL|Error|error:|panicked' "$log" | head -n 20 | sed 's/^/    | /'
            echo "    | ... last lines:"
            tail -n 15 "$log" | sed 's/^/    | /'
        fi
    fi
}

# ---------------------------------------------------------------- cases
D="$TMP/data"; mkdir -p "$D"

case_selftest() { py "$HERE/selftest.py" "$TMP/selftest"; }

gen_ml()  { [ -f "$D/ml.raw" ] || by generate marschner-lobb --size 77x50x33 --dtype u16 "$D/ml.raw"; }
gen_mb()  { [ -f "$D/mb.raw" ] || by generate mandelbulb --size 64 --dtype u8 "$D/mb.raw"; }

case_generate() {
    gen_ml; gen_mb
    ls -l "$D"
    local s; s="$(sidecar_of "$D/ml.raw")"; cat "$s"; echo
    py - "$s" "$D/ml.raw" <<'EOF'
import json, os, sys
s = json.load(open(sys.argv[1]))
assert s["dims"] == [77, 50, 33], f"sidecar dims {s['dims']} != [77, 50, 33]"
assert s["dtype"] in ("u16", "uint16"), s["dtype"]
n = 77 * 50 * 33 * 2 + int(s.get("header_bytes", 0))
assert os.path.getsize(sys.argv[2]) == n, f"raw size {os.path.getsize(sys.argv[2])} != {n}"
print("sidecar ok")
EOF
}

case_ml_u16() {
    gen_ml
    by convert "$D/ml.raw" "$D/ml.zarr" --brick 16 --shard 32
    check "$D/ml.zarr" --raw "$D/ml.raw" --sidecar "$(sidecar_of "$D/ml.raw")" \
        --dims 77 50 33 --dtype u16 --brick 16 --shard 32 --compression lz4
}

case_mb_u8() {
    gen_mb
    by convert "$D/mb.raw" "$D/mb.zarr" --brick 16 --shard 32
    check "$D/mb.zarr" --raw "$D/mb.raw" --sidecar "$(sidecar_of "$D/mb.raw")" \
        --dims 64 64 64 --dtype u8 --brick 16 --shard 32 --compression lz4
}

case_mb_labels() {
    gen_mb
    by convert "$D/mb.raw" "$D/mb_labels.zarr" --brick 16 --shard 32 --labels
    check "$D/mb_labels.zarr" --raw "$D/mb.raw" --sidecar "$(sidecar_of "$D/mb.raw")" \
        --dims 64 64 64 --dtype u8 --brick 16 --shard 32 --labels
}

case_mb_zstd() {
    gen_mb
    by convert "$D/mb.raw" "$D/mb_zstd.zarr" --brick 16 --shard 32 --compression zstd
    check "$D/mb_zstd.zarr" --raw "$D/mb.raw" --dims 64 64 64 --dtype u8 \
        --brick 16 --shard 32 --compression zstd
}

case_ml_nocomp() {
    gen_ml
    by convert "$D/ml.raw" "$D/ml_none.zarr" --brick 16 --shard 32 --compression none
    check "$D/ml_none.zarr" --raw "$D/ml.raw" --dims 77 50 33 --dtype u16 \
        --brick 16 --shard 32 --compression none
}

case_ml_defaults() {
    gen_ml
    by convert "$D/ml.raw" "$D/ml_default.zarr"
    check "$D/ml_default.zarr" --raw "$D/ml.raw" --dims 77 50 33 --dtype u16 \
        --brick 64 --shard 512 --compression lz4
}

case_overwrite() {
    gen_ml
    by convert "$D/ml.raw" "$D/ow.zarr" --brick 16 --shard 32
    # a second conversion over an existing store needs --overwrite ...
    if by convert "$D/ml.raw" "$D/ow.zarr" --brick 16 --shard 32; then
        echo "FAIL converting onto an existing store without --overwrite succeeded"; return 1
    fi
    # ... and with it replaces the old pyramid cleanly (mandelbulb data this time)
    gen_mb
    by convert "$D/mb.raw" "$D/ow.zarr" --brick 16 --shard 32 --overwrite
    check "$D/ow.zarr" --raw "$D/mb.raw" --dims 64 64 64 --dtype u8 --brick 16 --shard 32
}

case_memory_budget() {
    # a volume larger than the memory budget; peak RSS must stay within it
    [ -f "$D/big.raw" ] || by generate marschner-lobb --size 400x300x260 --dtype u16 "$D/big.raw" --quiet
    echo "+ brickyard convert big.raw --memory 56MiB (peak RSS measured)" >&2
    timeout "$CMD_TIMEOUT" "$PY" - 56 "$BIN" convert "$D/big.raw" "$D/big.zarr" \
        --brick 16 --shard 64 --memory 56MiB --quiet <<'EOF_PY'
import resource, subprocess, sys
budget = float(sys.argv[1])
r = subprocess.run(sys.argv[2:])
peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
print(f"brickyard exit {r.returncode}, peak RSS {peak:.1f} MiB (budget {budget:g} MiB, input 59.5 MiB)")
if r.returncode:
    sys.exit(r.returncode)
if peak > budget:
    print(f"FAIL peak RSS {peak:.1f} MiB exceeds --memory {budget:g}MiB")
    sys.exit(3)
EOF_PY
    check "$D/big.zarr" --raw "$D/big.raw" --dims 400 300 260 --dtype u16 --brick 16 --shard 64 \
        --no-ome-zarr-py
}

mk_inputs() { [ -f "$D/inputs/.done" ] || { py "$HERE/make_inputs.py" "$D/inputs" && touch "$D/inputs/.done"; }; }

case_raw_be_i16_2ch() {
    mk_inputs
    by convert "$D/inputs/be_i16_2ch.raw" "$D/be.zarr" --dims 37x29x21 --dtype i16 \
        --endian big --spacing 1,1,3 --channels 2 --header-bytes 128 --brick 16 --shard 32
    check "$D/be.zarr" --raw "$D/inputs/be_i16_2ch.raw" --dims 37 29 21 --dtype i16 \
        --endian big --channels 2 --header-bytes 128 --spacing 1 1 3 --brick 16 --shard 32
}

case_raw_f32_unit() {
    mk_inputs
    by convert "$D/inputs/f32.raw" "$D/f32.zarr" --brick 16 --shard 32 --unit nanometer
    check "$D/f32.zarr" --raw "$D/inputs/f32.raw" --sidecar "$D/inputs/f32.raw.json" \
        --brick 16 --shard 32 --unit nanometer
}

case_raw_labels_ties() {
    mk_inputs
    by convert "$D/inputs/ties_u16.raw" "$D/ties.zarr" --labels --brick 8 --shard 16
    check "$D/ties.zarr" --raw "$D/inputs/ties_u16.raw" --sidecar "$D/inputs/ties_u16.raw.json" \
        --labels --brick 8 --shard 16
}

case_nrrd() {
    mk_inputs
    by convert "$D/inputs/vol.nrrd" "$D/nrrd.zarr" --brick 16 --shard 32
    check "$D/nrrd.zarr" --npy "$D/inputs/vol_nrrd.npy" --spacing 0.8 0.8 2.0 --brick 16 --shard 32
}

case_nifti() {
    mk_inputs
    by convert "$D/inputs/vol.nii" "$D/nii.zarr" --brick 16 --shard 32
    check "$D/nii.zarr" --npy "$D/inputs/vol_nii.npy" --spacing 1.5 1.5 1.5 --brick 16 --shard 32
}

case_nifti_scaling() {
    # scl_slope/scl_inter applied as nibabel's get_fdata() does; --raw-values
    py "$HERE/nifti_scaling.py" "$BIN" "$D/nifti_scaling"
}

case_tiff() {
    mk_inputs
    by convert "$D/inputs/vol.tif" "$D/tif.zarr" --brick 16 --shard 32
    check "$D/tif.zarr" --npy "$D/inputs/vol_tif.npy" --brick 16 --shard 32
    by convert "$D/inputs/vol_f16.tif" "$D/tif_f16.zarr" --brick 8 --shard 16
    check "$D/tif_f16.zarr" --npy "$D/inputs/vol_f16_tif.npy" --brick 8 --shard 16
}

case_reconvert() {
    # brickyard's own OME-Zarr 0.5 output as input
    gen_ml
    [ -d "$D/ml.zarr" ] || by convert "$D/ml.raw" "$D/ml.zarr" --brick 16 --shard 32
    by convert "$D/ml.zarr" "$D/ml_again.zarr" --brick 8 --shard 16
    check "$D/ml_again.zarr" --raw "$D/ml.raw" --dims 77 50 33 --dtype u16 --brick 8 --shard 16
}

case_generate_zarr() {
    by generate mandelbulb --size 48 --dtype u8 "$D/gen48.zarr" --brick 16 --shard 32
    by generate mandelbulb --size 48 --dtype u8 "$D/gen48.raw"
    check "$D/gen48.zarr" --raw "$D/gen48.raw" --sidecar "$(sidecar_of "$D/gen48.raw")"
}

case_info_json() {
    gen_ml
    [ -d "$D/ml.zarr" ] || by convert "$D/ml.raw" "$D/ml.zarr" --brick 16 --shard 32
    by info "$D/ml.zarr"
    by info "$D/ml.zarr" --json > "$D/info.json"
    cat "$D/info.json"
    py -c 'import json,sys; d=json.load(open(sys.argv[1])); print("info --json parses:", type(d).__name__)' "$D/info.json"
}

write_refs() { [ -f "$D/ref/.done" ] || { py "$HERE/write_reference.py" "$D/ref" && touch "$D/ref/.done"; }; }
case_reference() {
    local name="$1"
    write_refs
    by convert "$D/ref/$name.zarr" "$D/conv_$name.zarr" --brick 16 --shard 32
    py "$HERE/check_roundtrip.py" "$D/ref/$name.zarr" "$D/conv_$name.zarr" --brick 16 --shard 32
}

# `brickyard process` against scipy.ndimage (filters, labels, statistics),
# and jobs killed at random points (the store stays as it was).
case_process() { py "$HERE/check_process.py" "$BIN" "$TMP/process_$1" "$1"; }

# s3:// stores against moto's S3 server (signed, anonymous, private/public)
case_s3() { py "$HERE/check_s3.py" "$BIN" "$TMP/s3"; }

# ---------------------------------------------------------------- run
run_case selftest            case_selftest
run_case generate_raw        case_generate
run_case ml_u16_b16s32       case_ml_u16
run_case mandelbulb_u8       case_mb_u8
run_case mandelbulb_labels   case_mb_labels
run_case mandelbulb_zstd     case_mb_zstd
run_case ml_uncompressed     case_ml_nocomp
run_case ml_default_brick    case_ml_defaults
run_case overwrite           case_overwrite
run_case raw_flags_be_i16_2ch case_raw_be_i16_2ch
run_case raw_f32_unit        case_raw_f32_unit
run_case raw_labels_ties     case_raw_labels_ties
run_case nrrd_i16_gzip       case_nrrd
run_case nifti_u16           case_nifti
run_case nifti_scaling       case_nifti_scaling
run_case tiff_u8             case_tiff
run_case reconvert_omezarr05 case_reconvert
run_case generate_zarr       case_generate_zarr
run_case info_json           case_info_json
run_case memory_budget       case_memory_budget
run_case process_generated   case_process generated
run_case process_nuclei      case_process nuclei
run_case process_crash       case_process crash
run_case s3_moto             case_s3
for ref in ome04_v2_u16 v3_plain_u16 v3_sharded_u16 ome05_2ch_u8 v3_f32_be v2_i16_be_F v2_u16_zlib \
    v2_i16_bz2 v2_i16_lz4 v3_u16_lz4 v2_u64 v3_i64_sharded; do
    run_case "ref_$ref" case_reference "$ref"
done

# non-fatal findings (e.g. NGFF "SHOULD"s), one line per case and message
for log in "$TMP"/logs/*.log; do
    [ -f "$log" ] || continue
    w="$(grep -h ': warning: ' "$log" | sed 's/^[a-z_]*: warning: //' | sort -u | paste -sd ';' - | sed 's/;/; /g')"
    [ -z "$w" ] || echo "interop: warning [$(basename "$log" .log)] $w"
done

if [ "$failed" -eq 0 ] && [ "${INTEROP_KEEP:-0}" != "1" ]; then
    rm -rf "$TMP"
else
    echo "interop: outputs and logs kept in $TMP"
fi
[ "$failed" -eq 0 ] || echo "interop: failed cases: ${failed_names[*]}"
echo "interop: $passed passed, $failed failed"
[ "$failed" -eq 0 ]
