#!/bin/bash
# usage: bash docs/training/grpo_s56/eval_candidate.sh CKPT LABEL -- session 56: one GRPO candidate on
#  1. acceleration with room to speed up, position drive, motorway_merge (300 s) and game/ramp (200 s), seed 0,
#  2. full-horizon runs, seed 0: position drive (with and without the safety layer) on motorway_merge and game/ramp, commands drive on game/ramp and game/grid6
#     (natives: docs/simulate/<scenario>_native.json, the report's).
#  3. the GRPO point's validation replicate (8 scenes, seeds 0-4, top-5; the pretrained start's side reused from session 54;
#     the shipped nano's own row is docs/eval_s54/val_shr_16.json),
# Outputs: docs/training/grpo_s56/LABEL/ (val.json, room_*.txt, runs' summaries) and runs/s56_LABEL/.
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
C=${1:?checkpoint}; L=${2:?label}
O=docs/training/grpo_s56/$L; mkdir -p "$O"
for s in "motorway_merge 300" "sumo-game-ramp 200"; do
  set -- $s
  python docs/simulate/filter_holds_s55/diag_room_acceleration.py --scenario $1 --end $2 --drive position --checkpoint "$C" > "$O/room_$1.txt" 2>&1
done
R=runs/s56_$L
python examples/full_horizon_runs.py --out $R/position --seed 0 --scenarios motorway_merge sumo-game-ramp --checkpoint "$C" --modes position position-raw > "$O/position.log" 2>&1
python examples/full_horizon_runs.py --out $R/commands --seed 0 --scenarios sumo-game-ramp sumo-game-grid6 --checkpoint "$C" --modes commands > "$O/commands.log" 2>&1
for m in position commands; do mkdir -p "$O/$m"; cp $R/$m/*.json "$O/$m/"; done
python scripts/eval_grpo_vs_pretrained.py --pretrained runs/s45_slow01/final --sampler topk:5 --threads 1 --grpo "$C" \
  --data data/generated/default/val --reuse-pretrained docs/eval_s54/val_nano40.json --out "$O/val.json" > "$O/val.log" 2>&1

