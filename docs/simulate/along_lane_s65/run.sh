#!/bin/bash
# Session 65: the position drive with the along-lane rules, seeds 0-2 on all 8 scenarios and the roundabout's seeds 3-5,
# against native on the same demand and seed (native rows reused from the earlier runs named below, copied in first).
# One thread per run; two side by side took ~25 min. Earlier rows: seed 0 runs/ship64_s0, seeds 1-2 runs/jx63pkg_sS,
# roundabout seeds 3-5 runs/jx63pkg_rb_sS (the position drive as of sessions 63-64).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
for S in 0 1 2; do
  B=$([ $S = 0 ] && echo runs/ship64_s0 || echo runs/jx63pkg_s$S)
  mkdir -p runs/s65e_s$S && cp $B/*_native.json runs/s65e_s$S/
  python examples/full_horizon_runs.py --modes native position --reuse native --seed $S --out runs/s65e_s$S
done
for S in 3 4 5; do
  mkdir -p runs/s65e_rb_s$S && cp runs/jx63pkg_rb_s$S/roundabout_native.json runs/s65e_rb_s$S/
  python examples/full_horizon_runs.py --scenarios roundabout --modes native position --reuse native --seed $S \
    --out runs/s65e_rb_s$S
done
python scripts/compare_full_horizon.py --mode position --events --queues before=runs/ship64_s0/report.json \
  before=runs/jx63pkg_s1/report.json before=runs/jx63pkg_s2/report.json after=runs/s65e_s0/report.json \
  after=runs/s65e_s1/report.json after=runs/s65e_s2/report.json > docs/simulate/along_lane_s65/position_seeds0to2.md
# seeds 3-4, before (a worktree of b3838c4, the package at session 64) and after, native run in each:
#   git worktree add /tmp/before b3838c4 && (cd /tmp/before && PYTHONPATH=$PWD python examples/full_horizon_runs.py \
#     --modes native position --seed S --out <repo>/runs/s65x_before_sS)
for S in 3 4; do
  python examples/full_horizon_runs.py --modes native position --seed $S --out runs/s65e_s$S
done
python scripts/compare_full_horizon.py --mode position --events --queues before=runs/s65x_before_s3/report.json \
  before=runs/s65x_before_s4/report.json after=runs/s65e_s3/report.json after=runs/s65e_s4/report.json \
  > docs/simulate/along_lane_s65/position_seeds3to4.md
