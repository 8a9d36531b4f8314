#!/bin/bash
# usage: bash docs/simulate/quantile_s53/run.sh -- session 53's runs of the commands drive's token sampler: the median rule
# centred on a higher quantile of the policy's forward travel (quantile:Q,0.1), shipped r1sim-nano, one thread each.
# Natives are reused: seed 0 from docs/simulate, seeds 1-2 from runs/med47_cmd_sS, seeds 3-7 from runs/med47_ramp_median_sS
# (python examples/full_horizon_runs.py --out runs/med47_cmd_sS --seed S --modes native, and the same with
# --scenarios sumo-game-ramp sumo-game-grid6 roundabout for seeds 3-7, make them). Output: runs/q53*; the reports kept
# are copied into docs/simulate/quantile_s53 by hand (report.json / report.md / *_commands.json).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
natives() {  # natives() SEED DIR
  if [ "$1" = 0 ]; then cp docs/simulate/*_native.json "$2"/
  elif [ "$1" -le 2 ]; then cp runs/med47_cmd_s$1/*_native.json "$2"/
  else cp runs/med47_ramp_median_s$1/*_native.json "$2"/; fi
}
three="--scenarios sumo-game-ramp sumo-game-grid6 roundabout"
# 1. screening on the three scenarios under 98%, seeds 0-2 (the median rows are session 52's runs/d51_ntop5_30_sS)
for P in "60 0.6" "65 0.65" "70 0.7" "80 0.8"; do
  set -- $P; L=$1; Q=$2
  for S in 0 1 2; do
    O=runs/q53_q${L}_s$S; mkdir -p $O; natives $S $O
    python examples/full_horizon_runs.py --out $O --seed $S --sampler quantile:$Q,0.1 --modes native commands --reuse native $three > $O.log 2>&1
  done
done
# 2. the chosen quantile on all eight scenarios, seeds 0-2
for S in 0 1 2; do
  O=runs/q53all_q70_s$S; mkdir -p $O; natives $S $O
  python examples/full_horizon_runs.py --out $O --seed $S --sampler quantile:0.7,0.1 --modes native commands --reuse native > $O.log 2>&1
done
# 3. seeds 3-7 on the three scenarios, median and 0.7 quantile side by side
for S in 3 4 5 6 7; do
  for P in "med median:0.1" "q70 quantile:0.7,0.1"; do
    set -- $P
    O=runs/q53_${1}_s$S; mkdir -p $O; natives $S $O
    python examples/full_horizon_runs.py --out $O --seed $S --sampler "$2" --modes native commands --reuse native $three > $O.log 2>&1
  done
done
# 4. the position drive with the 0.7 quantile, seed 0 (not adopted: more collision events)
O=runs/q53pos_q70_s0; mkdir -p $O; natives 0 $O
python examples/full_horizon_runs.py --out $O --seed 0 --sampler quantile:0.7,0.1 --modes native position --reuse native > $O.log 2>&1
