#!/bin/bash
# usage: bash docs/simulate/candidate_s53/run_ship_drop_in.sh -- session 53's drop-in reruns with the shipped r1sim-nano
# (grpo_s52_nano_top5 @ 40) on one thread: every mode at seed 0 (natives of docs/simulate and the commands rows of
# runs/at40q_s0, the same weights run with the drive's default by runs of this session:
#   python examples/full_horizon_runs.py --out runs/at40q_sS --seed S --checkpoint docs/training/runs/grpo_s52_nano_top5/final_it40 --modes native commands --reuse native
# with the natives copied in), then the position drive at seeds 1 and 2 (natives of runs/med47_cmd_sS).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
for d in runs/at40q_s0 runs/med47_cmd_s1 runs/med47_cmd_s2; do
  [ -d $d ] || { echo "$0: $d is missing: it holds the reused rows (runs/at40q_s0: the command above; runs/med47_cmd_sS: python examples/full_horizon_runs.py --out runs/med47_cmd_sS --seed S --modes native)" >&2; exit 1; }
done
O=runs/ship53_nano_s0; mkdir -p $O
cp docs/simulate/*_native.json $O/ && cp runs/at40q_s0/*_commands.* $O/
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw --reuse native commands > $O.log 2>&1
for S in 1 2; do
  O=runs/ship53_pos_s$S; mkdir -p $O; cp runs/med47_cmd_s$S/*_native.json $O/
  python examples/full_horizon_runs.py --out $O --seed $S --modes native position --reuse native > $O.log 2>&1
done
touch runs/ship53_drop_in.done
# then: seed 0 into docs/simulate (report + per-mode JSONs and pictures), seeds 1-2 into docs/simulate/candidate_s53
O=runs/ship53_nano_s0
cp $O/report.md $O/report.json $O/*_commands.json $O/*_commands.time_space.png $O/*_position.json $O/*_position.time_space.png \
   $O/*_position-raw.json $O/*_position-raw.time_space.png $O/*_time_space.png docs/simulate/
for S in 1 2; do
  D=docs/simulate/candidate_s53/position_nano53_s$S; mkdir -p $D
  cp runs/ship53_pos_s$S/report.json runs/ship53_pos_s$S/report.md runs/ship53_pos_s$S/*_position.json $D/
done
