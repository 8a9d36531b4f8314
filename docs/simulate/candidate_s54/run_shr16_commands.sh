#!/bin/bash
# usage: bash docs/simulate/candidate_s54/run_shr16_commands.sh -- session 54: grpo_s54_shr @ 16 in the default commands
# drive, the 8 scenarios, seeds 0-2, natives reused (seed 0: docs/simulate; seeds 1-2: runs/med47_cmd_sS, made by
#   python examples/full_horizon_runs.py --out runs/med47_cmd_sS --seed S --modes native)
# needs the checkpoint: runs/grpo_s54_shr_24/ckpt-000016 (docs/eval_s54/shr24.sh) or the bundled r1sim-grpo (same weights)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
CK=${CK:-r1sim-grpo}
run() {
  S=$1; O=runs/shr16_cmd_s$S; mkdir -p $O
  if [ $S = 0 ]; then cp docs/simulate/*_native.json $O/; else cp runs/med47_cmd_s$S/*_native.json $O/; fi
  python examples/full_horizon_runs.py --out $O --seed $S --checkpoint $CK --modes native commands --reuse native > $O.log 2>&1
}
(run 0; run 2) &
run 1
wait
