#!/bin/bash
# usage: bash docs/training/grpo_s56/run_more_only24.sh -- session 56: grpo_s56_ph_only @ 24 on motorway_merge without the
# safety layer, seeds 1-2 (as docs/simulate/candidate_s55 ran both nanos), then the position drive on the other bundled
# networks at seed 0 (natives: docs/simulate).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
C=docs/training/runs/grpo_s56_ph_only/ckpt-000024
O=docs/training/grpo_s56/only_24
for S in 1 2; do
  r1sim simulate --network motorway_merge --drive position --safety none --standstill-handoff 0 --seed $S --end 900 \
    --checkpoint $C --json $O/raw_motorway_merge/mm_raw_s$S.json --no-progress > runs/s56_only_24/raw_s$S.log 2>&1
done
python examples/full_horizon_runs.py --out runs/s56_only_24/position_rest --seed 0 --checkpoint $C --modes position \
  --scenarios lane_drop urban_intersection roundabout urban_grid > runs/s56_only_24/position_rest.log 2>&1
mkdir -p $O/position_rest && cp runs/s56_only_24/position_rest/*_position.json $O/position_rest/
