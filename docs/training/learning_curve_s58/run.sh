#!/bin/bash
# usage: bash docs/training/learning_curve_s58/run.sh -- session 58's learning curve: session 57's points (cached in the json
# copied from learning_curve_s57) + the two GRPO runs of the lent GPU from the shipped r1sim-nano on the position drive's
# closed-loop windows (16 x 32 rollouts per iteration): grpo_gpu_s58_ph (control) @ 9 / 11 and grpo_gpu_s58_ph_speedup
# (agents whose reference speeds up weighted 4x) @ 6 / 9 and grpo_gpu_s58_ph_speedup_k32 (the same, top-32 rollouts) @ 10
# (runs/grpo_gpu_s58_*: configs/grpo_gpu_s58_ph{,_speedup,_speedup_k32}.yaml)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
python -m r1sim_sumo.train.learning_curve --checkpoint runs/grpo_s56_ph_only/ckpt-000024 \
  --checkpoint runs/grpo_gpu_s58_ph/ckpt-000009 --checkpoint runs/grpo_gpu_s58_ph/final \
  --checkpoint runs/grpo_gpu_s58_ph_speedup/ckpt-000006 --checkpoint runs/grpo_gpu_s58_ph_speedup/ckpt-000009 \
  --checkpoint runs/grpo_gpu_s58_ph_speedup_k32/ckpt-000010 \
  --per-network 5 --threads 1 --val-tokens '' --out docs/training/learning_curve_s58
