#!/bin/bash
# usage: bash docs/training/ship_s57/run_position_seeds.sh SEED... -- session 57: the shipped r1sim-nano (grpo_s56_ph_only
# @ 24) in the position drive (safety layer on), the 8 scenarios, one seed after another on one thread, native rerun
# beside it (same seed and demand). Outputs runs/ship57_pos_sS and docs/training/ship_s57/position_sS/report.{md,json}.
# The previous nano's seeds 0-2 with the same command: docs/simulate/candidate_s54/position_grpo54_sS.
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
for S in "$@"; do
  O=runs/ship57_pos_s$S; mkdir -p $O
  python examples/full_horizon_runs.py --out $O --seed $S --modes native position > $O.log 2>&1 || { tail $O.log; exit 1; }
  mkdir -p docs/training/ship_s57/position_s$S && cp $O/report.md $O/report.json docs/training/ship_s57/position_s$S/
done
