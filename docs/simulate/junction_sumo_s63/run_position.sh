#!/bin/bash
# usage: bash docs/simulate/junction_sumo_s63/run_position.sh SEED [raw] -- session 63: the shipped r1sim-nano in the
# position drive (safety layer on, every default: SUMO drives a vehicle through each junction where it may have to
# stop, from max(20 m, 3 s x its allowed speed) before the line), the 8 scenarios on one thread (`raw`: also the position
# drive without the safety layer); native's rows reused from session 62's runs of the same seed (runs/wl62pkg_sS, which
# took them from session 58's runs: same demand; rerun them with `--modes native` where they are missing).
# Outputs $RUNS/jx63pkg_sS (RUNS defaults to runs/ of this checkout).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1 PYTHONPATH=$PWD
S=$1; RUNS=${RUNS:-runs}; O=$RUNS/jx63pkg_s$S; mkdir -p $O
MODES="native position"; [ "$2" = raw ] && MODES="native position position-raw"
for N in $RUNS/wl62pkg_s$S $RUNS/carry58_gains_s$S; do
  if ls $N/*_native.json > /dev/null 2>&1; then cp $N/*_native.json $O/; break; fi
done
REUSE=""; ls $O/*_native.json > /dev/null 2>&1 && REUSE="--reuse native"
python examples/full_horizon_runs.py --out $O --seed $S --modes $MODES $REUSE > $O.log 2>&1 || { tail $O.log; exit 1; }
