#!/bin/bash
# usage: bash docs/simulate/roundabout_s61/run_position.sh SEED... -- session 61: the shipped r1sim-nano in the
# position drive (safety layer on, every default: junction_turns="sumo" with the turns off the major road), the 8
# scenarios, one seed after another on one thread; native's rows reused from session 58's runs of the same seed
# (runs/carry58_gains_sS: same demand; rerun them with `--modes native` where they are missing).
# Outputs runs/turn61_sS and docs/simulate/roundabout_s61/sS/report.{md,json}.
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
for S in "$@"; do
  O=runs/turn61_s$S; mkdir -p $O
  N=runs/carry58_gains_s$S
  if ls $N/*_native.json > /dev/null 2>&1; then cp $N/*_native.json $O/; REUSE="--reuse native"; else REUSE=""; fi
  python examples/full_horizon_runs.py --out $O --seed $S --modes native position $REUSE > $O.log 2>&1 \
    || { tail $O.log; exit 1; }
  D=docs/simulate/roundabout_s61/s$S; mkdir -p $D && cp $O/report.md $O/report.json $D/
done
