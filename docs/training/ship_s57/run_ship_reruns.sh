#!/bin/bash
# Session 57: r1sim-nano becomes grpo_s56_ph_only @ 24 (shipped with
#   python -m r1sim_sumo.train.ship docs/training/runs/grpo_s56_ph_only/ckpt-000024 --name r1sim-nano).
# This reruns, on one thread, what was measured with the previous nano: its model card (in the bundled folder),
# issue 19's `r1sim ablate` Table III / II (IL = s45_slow01, GRPO-refined = the shipped nano; same scenes, rollouts,
# seeds and samplers as sessions 51 / 55) and the ego-RL table. The drop-in report (docs/simulate) is assembled from
# the same weights' session-56 runs (docs/training/grpo_s56/only_24/full_s0) by docs/training/ship_s57/assemble_drop_in.sh.
#   bash docs/training/ship_s57/run_ship_reruns.sh    (from the repository root; needs data/generated/default:
#   r1sim dataset build --config configs/dataset_eval_splits.yaml --out data/generated/default)
set -x
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
python -m r1sim_sumo.train.model_card r1sim_sumo/checkpoints/r1sim-nano --train data/generated/default/train \
  --heldout data/generated/default/val --closed-loop data/generated/default/test --max-heldout 400 --max-closed-loop 40 \
  --rollouts 8 --sampler topk:5 --threads 1 --train-desc 'the session-55 r1sim-nano (grpo_s54_shr @ 16) + 24 GRPO iterations of its recipe (shr, top-5) on closed-loop windows of its own position driving (configs/grpo_s56_ph_only.yaml, data configs/dataset_policy_history_pos.yaml); sessions 56-57' || exit 1
IL=runs/s45_slow01/final
[ -d $IL ] || { mkdir -p runs && cp -r docs/training/runs/s45_slow01 runs/; }
r1sim ablate --data data/generated/default/test --il $IL --grpo r1sim-nano --samplers topk:5 topk:32 entropy:16,80 \
  --rollouts 8 --seeds 0 1 2 3 4 --max-scenarios 8 --easy-hard-quantile 0.25 --threads 1 --out runs/ablate_s57 || exit 1
mkdir -p docs/training/ablate_s57 && cp runs/ablate_s57/ablation.md runs/ablate_s57/ablation.json runs/ablate_s57/*.png docs/training/ablate_s57/
python examples/train_ego_sb3.py --steps 20000 --episodes 20 --out runs/ego_sb3_s57 || exit 1
cp runs/ego_sb3_s57/results.md runs/ego_sb3_s57/episode.gif docs/ego_sb3/
echo DONE
