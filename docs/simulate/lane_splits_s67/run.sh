#!/bin/bash
# Session 67: the position drive's lane-split and lane-change-gate rules, measured against native on the same demand and
# seed; and the GRPO run continued on a lent GPU (grpo_gpu_s58_ph_speedup_k32 @ 56) in the same drive. One thread per
# run, two side by side (~30 min in all on this machine). Run from a snapshot worktree of the commit
# (git worktree add /tmp/s67 <commit> && cd /tmp/s67) so that edits do not change a run.
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
OUT=${OUT:-runs}
# urban_intersection, seeds 0-7 (the step table's rows: the same command at each step's commit, OUT=runs/s67<step>_sN)
for S in 0 1 2 3 4 5 6 7; do
  python examples/full_horizon_runs.py --scenarios urban_intersection --modes position --seed $S --out $OUT/s67z_s$S
done
# the other seven scenarios, seeds 0-2
for S in 0 1 2; do
  python examples/full_horizon_runs.py --scenarios lane_drop motorway_merge roundabout urban_grid sumo-game-ramp \
    sumo-game-cross sumo-game-grid6 --modes position --seed $S --out $OUT/s67ko_s$S
done
# urban_grid, seeds 3-7
for S in 3 4 5 6 7; do
  python examples/full_horizon_runs.py --scenarios urban_grid --modes position --seed $S --out $OUT/s67kg_s$S
done
# the policy continued on the GPU (its weights: docs/training/gpu_s67/README.md, "Run state"): urban_intersection seeds
# 0-7 and the other seven scenarios, seeds 0-2 (session 67 ran these at step j's commit 2067194, and urban_intersection
# also at step h's 432f7fd: OUT/s67k56_sN; the nano's rows at j: the three loops above with OUT/s67j_sN, s67jo_sN, s67jg_sN)
CK=runs/grpo_gpu_s58_ph_speedup_k32/ckpt-000056
for S in 0 1 2 3 4 5 6 7; do
  python examples/full_horizon_runs.py --scenarios urban_intersection --modes position --seed $S --out $OUT/s67k56j_s$S \
    --checkpoint $CK
done
for S in 0 1 2; do
  python examples/full_horizon_runs.py --scenarios lane_drop motorway_merge roundabout urban_grid sumo-game-ramp \
    sumo-game-cross sumo-game-grid6 --modes position --seed $S --out $OUT/s67k56o_s$S --checkpoint $CK
done
# the report's position rows (seed 0): session 66's native, commands and position-raw rows (code paths unchanged) with
# this session's position rows, the report rebuilt from them without running anything
mkdir -p $OUT/ship67_s0 && cp $OUT/ship66_s0/*_native.* $OUT/ship66_s0/*_commands.* $OUT/ship66_s0/*_position-raw.* $OUT/ship67_s0/
cp $OUT/s67ko_s0/*_position.* $OUT/s67z_s0/urban_intersection_position.* $OUT/ship67_s0/
python examples/full_horizon_runs.py --seed 0 --modes native commands position position-raw \
  --reuse native commands position position-raw --out $OUT/ship67_s0
# the tables, against session 66's runs (OUT/ship66_s0, OUT/s66z_sN, OUT/s66zo_sN: docs/simulate/networks_s66/run.sh),
# one folder per seed holding every scenario's runs of a variant
for S in 0 1 2 3 4 5 6 7; do mkdir -p $OUT/s66all_s$S $OUT/s67all_s$S; done
cp $OUT/ship66_s0/*.json $OUT/s66all_s0/ && cp $OUT/ship67_s0/*.json $OUT/s67all_s0/
for S in 1 2 3 4 5 6 7; do cp $OUT/s66z_s$S/*.json $OUT/s66all_s$S/; done
for S in 1 2; do cp $OUT/s66zo_s$S/*.json $OUT/s66all_s$S/ && cp $OUT/s67ko_s$S/*.json $OUT/s67all_s$S/; done
for S in 1 2 3 4 5 6 7; do cp $OUT/s67z_s$S/*.json $OUT/s67all_s$S/; done
for S in 3 4 5 6 7; do cp $OUT/s67kg_s$S/*.json $OUT/s67all_s$S/; done
for S in 0 1 2 3 4 5 6 7; do mkdir -p $OUT/k56all_s$S && cp $OUT/s67k56j_s$S/*.json $OUT/k56all_s$S/; done
for S in 0 1 2; do cp $OUT/s67k56o_s$S/*.json $OUT/k56all_s$S/; done
python scripts/pool_seed_runs.py --scenario urban_intersection --seeds 0-7 --native "$OUT/s66all_s{seed}" \
  "s66=$OUT/s66all_s{seed}" "s67=$OUT/s67all_s{seed}" "s67, policy @ 56=$OUT/k56all_s{seed}"
python scripts/pool_seed_runs.py --scenario urban_grid --seeds 0-7 --native "$OUT/s66all_s{seed}" \
  "s66=$OUT/s66all_s{seed}" "s67=$OUT/s67all_s{seed}"
for SC in motorway_merge lane_drop roundabout sumo-game-ramp sumo-game-cross sumo-game-grid6; do
  python scripts/pool_seed_runs.py --scenario $SC --seeds 0-2 --native "$OUT/s66all_s{seed}" \
    "s66=$OUT/s66all_s{seed}" "s67=$OUT/s67all_s{seed}" "s67, policy @ 56=$OUT/k56all_s{seed}"
done
