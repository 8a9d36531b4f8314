#!/bin/bash
# Session 66: the rebuilt urban_intersection and urban_grid and the position drive's lane-split keeper, measured against
# native on the same demand and seed. One thread per run, two side by side (~25 min in all on this machine). Run from a
# snapshot worktree of the commit (git worktree add /tmp/s66 <commit> && cd /tmp/s66) so edits do not change a run.
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
OUT=${OUT:-runs}
# seed 0, every scenario and mode: the report (docs/simulate/report.md)
python examples/full_horizon_runs.py --seed 0 --modes native commands position position-raw --out $OUT/ship66_s0
# seeds 1-2: the two rebuilt networks with the commands drive too, the other six scenarios native + position
for S in 1 2; do
  python examples/full_horizon_runs.py --scenarios urban_intersection urban_grid --modes native commands position \
    --seed $S --out $OUT/s66z_s$S
  python examples/full_horizon_runs.py --scenarios lane_drop motorway_merge roundabout sumo-game-ramp sumo-game-cross \
    sumo-game-grid6 --modes native position --seed $S --out $OUT/s66zo_s$S
done
# seeds 3-7 of the two rebuilt networks
for S in 3 4 5 6 7; do
  python examples/full_horizon_runs.py --scenarios urban_intersection urban_grid --modes native position --seed $S \
    --out $OUT/s66z_s$S
done
# SUMO's own drivers on the bundled networks (collision events with every check on)
python scripts/count_native_collisions.py --networks motorway_merge lane_drop roundabout urban_intersection urban_grid \
  --seeds 0 1 2 3 4 5
