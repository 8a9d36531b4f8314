#!/bin/bash
# usage: bash docs/training/learning_curve_s54/run.sh -- session 54's learning curve: session 53's checkpoints (cached in the
# json copied from learning_curve_s53) + the shr continuation @ 12 / 16 (shipped as r1sim-grpo) / 24 and gated @ 12
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
python -m r1sim_sumo.train.learning_curve --checkpoint runs/grpo_s45_slow01/final --checkpoint runs/grpo_s46_lr1e4/final \
  --checkpoint runs/grpo_s51_nudge/ckpt-000010 --checkpoint runs/grpo_s51_nudge/ckpt-000020 --checkpoint runs/grpo_s51_mix/final \
  --checkpoint runs/grpo_s51_lane_drop/final --checkpoint runs/grpo_s52_nano_top5/ckpt-000010 \
  --checkpoint runs/grpo_s52_nano_top5/ckpt-000020 --checkpoint runs/grpo_s52_nano_top5/ckpt-000030 \
  --checkpoint runs/grpo_s52_nano_top5/final_it40 --checkpoint runs/grpo_s52_nano_top5_60/ckpt-000050 \
  --checkpoint runs/grpo_s52_nano_top5_60/ckpt-000060 --checkpoint runs/grpo_s52_top5/final \
  --checkpoint runs/grpo_s54_gated/ckpt-000012 --checkpoint runs/grpo_s54_shr_24/ckpt-000012 \
  --checkpoint runs/grpo_s54_shr_24/ckpt-000016 --checkpoint runs/grpo_s54_shr_24/ckpt-000024 \
  --per-network 5 --threads 1 --val-tokens '' --out docs/training/learning_curve_s54
