#!/bin/bash
# usage: bash docs/training/learning_curve_s64/run.sh -- session 64's learning curve: session 58's points (cached in the
# json copied from learning_curve_s58: the shipped r1sim-nano = runs/grpo_s56_ph_only/ckpt-000024 and session 58's GPU
# runs) + the same two GPU runs continued on a lent H200 in session 64 (scripts/device_grpo_continue.sh) from iteration
# 11 (grpo_gpu_s58_ph, control: reward shr, top-5) and 10 (grpo_gpu_s58_ph_speedup_k32: speed-up weight 4, top-32) to 32:
# runs/grpo_gpu_s58_ph_c64 and runs/grpo_gpu_s58_ph_speedup_k32_c64 @ 24 and @ 32 (final).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
python -m r1sim_sumo.train.learning_curve --checkpoint runs/grpo_s56_ph_only/ckpt-000024 \
  --checkpoint runs/grpo_gpu_s58_ph/final --checkpoint runs/grpo_gpu_s58_ph_speedup_k32/ckpt-000010 \
  --checkpoint runs/grpo_gpu_s58_ph_c64/ckpt-000024 --checkpoint runs/grpo_gpu_s58_ph_c64/final \
  --checkpoint runs/grpo_gpu_s58_ph_speedup_k32_c64/ckpt-000024 --checkpoint runs/grpo_gpu_s58_ph_speedup_k32_c64/final \
  --per-network 5 --threads 1 --val-tokens '' --out docs/training/learning_curve_s64
