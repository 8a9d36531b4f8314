#!/bin/bash
# usage: bash docs/simulate/moved_speed_s59/tools/raw_mm.sh LABEL SEED [old] -- session 59: motorway_merge without the
# safety layer (position-raw) at SEED into runs/LABEL_sSEED; `old`: with the position drive as before session 59 (plans
# from SUMO's speed reading of a moved vehicle; sitecustomize.py beside this script, switched on by R1SIM_SUMOSPEED=1).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
L=$1; S=$2; O=runs/${L}_s$S; mkdir -p $O
E=""; [ "$3" = old ] && E="R1SIM_SUMOSPEED=1"
env $E PYTHONPATH=docs/simulate/moved_speed_s59/tools${PYTHONPATH:+:$PYTHONPATH} OMP_NUM_THREADS=1 \
  python examples/full_horizon_runs.py --out $O --seed $S --scenarios motorway_merge --modes native position-raw > $O.log 2>&1
