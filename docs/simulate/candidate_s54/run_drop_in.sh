#!/bin/bash
# usage: bash docs/simulate/candidate_s54/run_drop_in.sh commands|position -- session 54: r1sim-grpo (grpo_s54_shr @ 16) in
# the given drive (position: safety layer on), the 8 scenarios, seeds 0-2, natives reused (seed 0: docs/simulate;
# seeds 1-2: runs/med47_cmd_sS, made by  python examples/full_horizon_runs.py --out runs/med47_cmd_sS --seed S --modes native).
# Outputs runs/shr16_cmd_sS (commands) or runs/grpo54_pos_sS (position). CK=<checkpoint> runs another policy.
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
MODE=${1:?give commands or position}
CK=${CK:-r1sim-grpo}
case $MODE in commands) PRE=runs/shr16_cmd_s ;; position) PRE=runs/grpo54_pos_s ;; *) echo "$0: mode '$MODE': use commands or position" >&2; exit 2 ;; esac
run() {
  S=$1; O=$PRE$S; mkdir -p $O
  if [ $S = 0 ]; then cp docs/simulate/*_native.json $O/; else cp runs/med47_cmd_s$S/*_native.json $O/; fi
  python examples/full_horizon_runs.py --out $O --seed $S --checkpoint $CK --modes native $MODE --reuse native > $O.log 2>&1
}
(run 0; run 2) &
run 1
wait
