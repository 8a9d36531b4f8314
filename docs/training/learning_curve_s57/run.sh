#!/bin/bash
# usage: bash docs/training/learning_curve_s57/run.sh -- session 57's learning curve: session 54's points (cached in the json
# copied from learning_curve_s54) + session 56's GRPO runs on the position drive's closed-loop windows: ph_only @ 8 / 16 /
# 24 (shipped as r1sim-nano in session 57) and ph_mix @ 12 / 24 (runs/grpo_s56_ph_*: r1sim finetune --config
# configs/grpo_s56_ph_{only,mix}.yaml)
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
  --checkpoint runs/grpo_s56_ph_only/ckpt-000008 --checkpoint runs/grpo_s56_ph_only/ckpt-000016 \
  --checkpoint runs/grpo_s56_ph_only/ckpt-000024 --checkpoint runs/grpo_s56_ph_mix/ckpt-000012 \
  --checkpoint runs/grpo_s56_ph_mix/ckpt-000024 \
  --per-network 5 --threads 1 --val-tokens '' --out docs/training/learning_curve_s57
