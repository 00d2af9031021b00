#!/usr/bin/env bash
# Progressive DVR (sample accumulation) shared by MPI ranks: one rank
# against two, image- and data-parallel, with each rank's CPU seconds and
# peak memory (`/usr/bin/time` per rank). `mpirun -n N` binds each rank to
# a core when N is at most the core count, so 1 → 2 ranks is one core → two.
#
# usage: scripts/bench-mpi-savr.sh BRICKYARD STORE [SIZE] [FRAMES] [REPEATS]
#   BRICKYARD  built with --features brickyard/mpi
#   STORE      an OME-Zarr store
#   SIZE       image WxH (default 640x480); FRAMES accumulated (default 8)
set -euo pipefail
B=${1:?usage: bench-mpi-savr.sh BRICKYARD STORE [SIZE] [FRAMES] [REPEATS]}
STORE=${2:?store}
SIZE=${3:-640x480}
N=${4:-8}
REP=${5:-3}
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
OUT=$(mktemp -d)
trap 'rm -rf "$OUT"' EXIT
V="--size $SIZE --azimuth 30 --elevation 20 --progressive $N --backend cpu"
echo "# $(date -u +%FT%TZ) $(nproc) CPUs, $(lscpu | sed -n 's/^Model name: *//p'); store $STORE, $SIZE, $N frames"
for r in $(seq "$REP"); do
  # One rank draws as one process does; data-parallel ranks cannot end
  # rays early (sort-last), so they are measured beside one rank without
  # early termination ("data 1" below).
  for how in image data; do
    for n in 1 2; do
      X=""
      if [ "$how" = data ] && [ "$n" = 1 ]; then X=--no-early-termination; fi
      echo "## repetition $r: $how-parallel, $n rank(s) $X, load $(cut -d' ' -f1 /proc/loadavg)"
      # Per rank: user s, system s, wall s, peak RSS KiB.
      mpirun -n "$n" /usr/bin/time -f "rank-time %U %S %e %M" "$B" render "$STORE" $V $X \
        --distribute "$how" --out "$OUT/$how-$n.png" 2>&1 |
        grep -E "rank-time|accumulated [0-9]|ranks (drew|accumulated)|regions of" || true
    done
  done
done
