# Sourced by the web benchmarks: the three-channel MNI152 converted into
# $WORK/stores/mni3.ome.zarr (once) and $WORK/stores served with the web
# client by $BIN on a free loopback port ($PORT; the server is stopped when
# the script exits). Needs BIN and WORK set, and the current directory at
# the repository's root.
D="$(realpath ../shared/data)"
mkdir -p "$WORK/stores"
[ -d "$WORK/stores/mni3.ome.zarr" ] || "$BIN" convert "$D"/mni152-{t1,gm,wm}-u8.nii.gz \
    "$WORK/stores/mni3.ome.zarr" --channel-names t1,gm,wm --quiet
"$BIN" serve --web --quiet --port 0 "$WORK/stores" 2> "$WORK/serve.log" &
SRV=$!
trap 'kill $SRV' EXIT
sleep 1
PORT=$(head -1 "$WORK/serve.log" | sed -E 's/.*127\.0\.0\.1:([0-9]+).*/\1/')
