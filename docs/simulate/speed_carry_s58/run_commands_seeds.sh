#!/bin/bash
# usage: bash docs/simulate/speed_carry_s58/run_commands_seeds.sh CARRY SEED... -- session 58: the commands drive of the
# shipped r1sim-nano with `--speed-carry CARRY` on the three scenarios closest to issue 20's 98% (game/ramp, game/grid6,
# roundabout), natives reused from session 56's runs of the same weights and seed (runs/s56_only_24/commands_sS; rerun
# with `--modes native` where missing). Output runs/carry58_cmd_<CARRY>_sS; compared with session 56's by
#   python scripts/compare_seed_means.py nano=runs/s56_only_24/commands_s{1..7}/report.json carry=runs/carry58_cmd_gains_s{1..7}/report.json --mode commands --scenarios sumo-game-ramp sumo-game-grid6 roundabout
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
CARRY=$1; shift
three="--scenarios sumo-game-ramp sumo-game-grid6 roundabout"
for S in "$@"; do
  O=runs/carry58_cmd_${CARRY}_s$S; mkdir -p $O
  N=runs/s56_only_24/commands_s$S
  if ls $N/*_native.json > /dev/null 2>&1; then cp $N/*_native.* $O/; REUSE="--reuse native"; else REUSE=""; fi
  python examples/full_horizon_runs.py --out $O --seed $S --modes native commands $REUSE --speed-carry $CARRY $three > $O.log 2>&1 \
    || { tail $O.log; exit 1; }
done
