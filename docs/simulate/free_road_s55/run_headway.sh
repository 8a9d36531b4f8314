#!/bin/bash
# usage: bash docs/simulate/free_road_s55/run_headway.sh SEED Q H [scenarios...] -- session 55: the position drive with the
# free-road quantile Q where a leader H s or more ahead (not slower) still leaves the road free
# (r1sim simulate --free-road-quantile Q --free-road-headway H); natives reused as in run.sh. Output runs/fr55_qQ_hH_sS.
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
S=${1:?seed}; Q=${2:?quantile}; H=${3:?headway}; shift 3
SC=""; [ $# -gt 0 ] && SC="--scenarios $*"
O=runs/fr55_q${Q}_h${H}_s$S; mkdir -p $O
if [ $S = 0 ]; then cp docs/simulate/*_native.json $O/; else
  [ -d runs/med47_cmd_s$S ] || python examples/full_horizon_runs.py --out runs/med47_cmd_s$S --seed $S --modes native > runs/med47_cmd_s$S.log 2>&1
  cp runs/med47_cmd_s$S/*_native.json $O/; fi
python examples/full_horizon_runs.py --out $O --seed $S --modes native position --reuse native --free-road-quantile $Q --free-road-headway $H $SC > $O.log 2>&1
