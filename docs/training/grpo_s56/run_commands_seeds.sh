#!/bin/bash
# usage: bash docs/training/grpo_s56/run_commands_seeds.sh CKPT LABEL SEED... -- session 56: the commands drive of a candidate
# on the three scenarios under 98% with the session-55 nano (game/ramp, game/grid6, roundabout), natives first into the
# same folder (same demand and seed). Output runs/s56_LABEL/commands_sS; compared with the shipped nano by
#   python scripts/compare_seed_means.py nano55=<its 8 reports> LABEL=<these> --mode commands --scenarios sumo-game-ramp sumo-game-grid6 roundabout
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
C=${1:?checkpoint}; L=${2:?label}; shift 2
three="--scenarios sumo-game-ramp sumo-game-grid6 roundabout"
for S in "$@"; do
  O=runs/s56_$L/commands_s$S; mkdir -p $O
  python examples/full_horizon_runs.py --out $O --seed $S --checkpoint "$C" --modes native commands $three > $O.log 2>&1
done
