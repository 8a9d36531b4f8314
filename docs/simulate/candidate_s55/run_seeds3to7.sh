#!/bin/bash
# usage: bash docs/simulate/candidate_s55/run_seeds3to7.sh -- session 55: the commands drive of the new r1sim-nano on the
# three scenarios under 98% (game/ramp, game/grid6, roundabout), seeds 3-7, natives run first into the same folder
# (same demand and seed). Output runs/ship55_cmd_sS; compared with session 53's nano (docs/simulate/quantile_s53/q70_sS) by
#   python scripts/compare_seed_means.py nano53=docs/simulate/quantile_s53/q70_s3,... nano55=runs/ship55_cmd_s3,... --mode commands
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
three="--scenarios sumo-game-ramp sumo-game-grid6 roundabout"
for S in 3 4 5 6 7; do
  O=runs/ship55_cmd_s$S; mkdir -p $O
  python examples/full_horizon_runs.py --out $O --seed $S --modes native commands $three > $O.log 2>&1
done
touch runs/ship55_cmd.done
