#!/bin/bash
# usage: bash docs/simulate/candidate_s54/run_grpo_position.sh -- session 54: r1sim-grpo (grpo_s54_shr @ 16) in the position
# drive (safety layer on), the 8 scenarios, seeds 0-2, natives reused as in run_shr16_commands.sh; compare with the nano's
# position rows: seed 0 docs/simulate/report.json, seeds 1-2 docs/simulate/candidate_s53/position_nano53_sS/report.json
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
CK=${CK:-r1sim-grpo}
run() {
  S=$1; O=runs/grpo54_pos_s$S; mkdir -p $O
  if [ $S = 0 ]; then cp docs/simulate/*_native.json $O/; else cp runs/med47_cmd_s$S/*_native.json $O/; fi
  python examples/full_horizon_runs.py --out $O --seed $S --checkpoint $CK --modes native position --reuse native > $O.log 2>&1
}
(run 0; run 2) &
run 1
wait
