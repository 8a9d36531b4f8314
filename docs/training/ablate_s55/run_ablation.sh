#!/bin/bash
# Session 55: issue 19's `r1sim ablate` Table III / II rerun for the session-55 r1sim-nano (= r1sim-grpo, grpo_s54_shr @ 16).
# IL = s45_slow01 (the pretrained start of the whole lineage, as in session 51), GRPO-refined = the shipped weights
# (s45_slow01 + 116 GRPO iterations over five runs: grpo_s45_slow01 30, grpo_s46_lr1e4 20, grpo_s51_nudge 10,
# grpo_s52_nano_top5 40, grpo_s54_shr 16). Same held-out scenes, rollouts, seeds and samplers as session 51
# (docs/training/ablate_s51), whose SFT and GRPO-standard rows (15 iterations from the same IL) stay comparable.
#   bash docs/training/ablate_s55/run_ablation.sh   (from the repository root; needs data/generated/default/test:
#   r1sim dataset build --config configs/dataset_eval_splits.yaml --out data/generated/default)
set -x
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
IL=runs/s45_slow01/final
[ -d $IL ] || { mkdir -p runs && cp -r docs/training/runs/s45_slow01 runs/; }
r1sim ablate --data data/generated/default/test --il $IL --grpo r1sim-nano --samplers topk:5 topk:32 entropy:16,80 \
  --rollouts 8 --seeds 0 1 2 3 4 --max-scenarios 8 --easy-hard-quantile 0.25 --threads 1 --out runs/ablate_s55 || exit 1
mkdir -p docs/training/ablate_s55 && cp runs/ablate_s55/ablation.md runs/ablate_s55/ablation.json docs/training/ablate_s55/
cp runs/ablate_s55/*.png docs/training/ablate_s55/   # training_curves.png is empty: no fine-tune log among these models
echo DONE
