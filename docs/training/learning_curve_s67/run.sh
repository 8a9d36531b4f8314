#!/bin/bash
# usage: bash docs/training/learning_curve_s67/run.sh -- session 67's curve points: the shipped r1sim-nano and session 58's
# speed-up GRPO run continued on a lent H200 to iteration 56 (docs/training/gpu_s67). The test split is built here
# first (the default recipe's test seeds on the current networks; train/val one seed each, as a split may not be empty).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
if [ ! -d data/generated/default_testonly ]; then
  printf 'train_seeds: 1\nval_seeds: 1\nhighway_train_seeds: 0\nhighway_val_seeds: 0\n' > /tmp/default_testonly.yaml
  r1sim dataset build --config /tmp/default_testonly.yaml --out data/generated/default_testonly --workers 1
fi
if [ ! -d runs/grpo_gpu_s58_ph_speedup_k32/ckpt-000056 ]; then  # the iteration-56 weights from the committed run state
  mkdir -p runs && cp -r docs/training/runs/grpo_gpu_s58_ph_speedup_k32 runs/
  r1sim finetune --config runs/grpo_gpu_s58_ph_speedup_k32/config.yaml --resume --set device=cpu max_iters=56 \
    out_dir=runs/grpo_gpu_s58_ph_speedup_k32
  cp -r runs/grpo_gpu_s58_ph_speedup_k32/final runs/grpo_gpu_s58_ph_speedup_k32/ckpt-000056
fi
if [ ! -d runs/grpo_k32_at32/final ]; then  # the run's iteration-32 weights from session 64's committed state (553213c)
  mkdir -p runs/grpo_k32_at32/state
  for f in state/state.safetensors state/state.json config.yaml log.csv; do
    git show 553213c:docs/training/runs/grpo_gpu_s58_ph_speedup_k32/$f > runs/grpo_k32_at32/$f
  done
  r1sim finetune --config runs/grpo_k32_at32/config.yaml --resume --set device=cpu max_iters=32 out_dir=runs/grpo_k32_at32
fi
python -m r1sim_sumo.train.learning_curve --checkpoint r1sim-nano --checkpoint runs/grpo_k32_at32/final \
  --checkpoint runs/grpo_gpu_s58_ph_speedup_k32/ckpt-000056 \
  --data data/generated/default_testonly/test --per-network 5 --threads 1 --val-tokens '' --out docs/training/learning_curve_s67
