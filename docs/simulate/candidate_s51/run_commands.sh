#!/bin/bash
# usage: bash docs/simulate/candidate_s51/run_commands.sh LABEL CKPT SEED... -- commands drive, full horizon, the 8 scenarios, natives reused
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
L=$1; C=$2; shift 2
export OMP_NUM_THREADS=1
for S in "$@"; do
  O=runs/d51_${L}_s$S; mkdir -p $O
  if [ "$S" = 0 ]; then cp docs/simulate/*_native.json $O/; else cp runs/med47_cmd_s$S/*_native.json $O/; fi
  python examples/full_horizon_runs.py --out $O --seed $S --checkpoint $C --modes native commands --reuse native > $O.log 2>&1
done
touch runs/d51_${L}.done
