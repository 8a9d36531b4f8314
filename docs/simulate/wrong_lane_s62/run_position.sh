#!/bin/bash
# usage: bash docs/simulate/wrong_lane_s62/run_position.sh SEED [raw] -- session 62: the shipped r1sim-nano in the
# position drive (safety layer on, every default: a vehicle in a lane that does not continue its route is SUMO's
# within 10 s x its allowed speed of the lane's end), the 8 scenarios on one thread (`raw`: also the position drive
# without the safety layer); native's rows reused from session 58's runs of the same seed (runs/carry58_gains_sS: same
# demand; rerun them with `--modes native` where they are missing). Outputs runs/wl62pkg_sS.
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
S=$1; O=runs/wl62pkg_s$S; mkdir -p $O
MODES="native position"; [ "$2" = raw ] && MODES="native position position-raw"
N=runs/carry58_gains_s$S
if ls $N/*_native.json > /dev/null 2>&1; then cp $N/*_native.json $O/; REUSE="--reuse native"; else REUSE=""; fi
python examples/full_horizon_runs.py --out $O --seed $S --modes $MODES $REUSE > $O.log 2>&1 || { tail $O.log; exit 1; }
