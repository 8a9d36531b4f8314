#!/bin/bash
# usage: bash docs/simulate/free_road_s55/run.sh SEED Q -- session 55: the position drive (safety layer on) with the
# free-road quantile Q (r1sim simulate --free-road-quantile Q), the 8 scenarios, natives reused (seed 0: docs/simulate;
# seeds 1-2: runs/med47_cmd_sS, made by  python examples/full_horizon_runs.py --out runs/med47_cmd_sS --seed S --modes native).
# Output runs/fr55_qQ_sS. The reference (the same policy without it) is the seed's position row of
# docs/simulate/report.md (seed 0) or docs/simulate/candidate_s54/position_grpo54_sS (seeds 1-2).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
S=${1:?give a seed}; Q=${2:?give a quantile, e.g. 0.7}
O=runs/fr55_q${Q}_s$S; mkdir -p $O
if [ $S = 0 ]; then cp docs/simulate/*_native.json $O/; else
  [ -d runs/med47_cmd_s$S ] || python examples/full_horizon_runs.py --out runs/med47_cmd_s$S --seed $S --modes native > runs/med47_cmd_s$S.log 2>&1
  cp runs/med47_cmd_s$S/*_native.json $O/; fi
python examples/full_horizon_runs.py --out $O --seed $S --modes native position --reuse native --free-road-quantile $Q > $O.log 2>&1
