#!/bin/bash
# Session 51: issue 19's full `r1sim ablate` rerun with the session-46 nano's lineage.
# IL = s45_slow01 (the nano's pretrained start), GRPO-refined = grpo_s45_slow01 @ 15 (the nano's own GRPO recipe),
# every other fine-tune 15 iterations of configs/grpo_s45_slow01.yaml with only the method / reward changed.
#   bash docs/training/ablate_s51/run_ablation.sh   (from the repository root; data as in configs/grpo_s45_slow01.yaml)
# On a fresh machine runs/s45_slow01/final comes from docs/training/runs/s45_slow01 (mkdir -p runs && cp -r
# docs/training/runs/s45_slow01 runs/); without session 45's runs/grpo_s45_slow01/ckpt-000015, the GRPO-refined row is
# retrained: 15 iterations of the same recipe.
set -x
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
T=runs/ablate_s51/train
IL=runs/s45_slow01/final
[ -d $IL ] || { mkdir -p runs && cp -r docs/training/runs/s45_slow01 runs/; }
if [ -d runs/grpo_s45_slow01/ckpt-000015 ]; then
  mkdir -p $T/grpo && cp -r runs/grpo_s45_slow01/ckpt-000015 $T/grpo/final && head -16 runs/grpo_s45_slow01/log.csv > $T/grpo/log.csv
else
  [ -f $T/grpo/final/model.safetensors ] || r1sim finetune --config configs/grpo_s45_slow01.yaml --set max_iters=15 keep_every=0 out_dir=$T/grpo
fi
for spec in "sft method=sft" "grpo-std method=grpo-std"; do key=${spec%% *}
  [ -f $T/$key/final/model.safetensors ] || r1sim finetune --config configs/grpo_s45_slow01.yaml --set ${spec#* } max_iters=15 keep_every=0 out_dir=$T/$key
done
r1sim ablate --data data/generated/default/test --il $IL --sft $T/sft/final \
  --grpo-std $T/grpo-std/final --grpo $T/grpo/final --samplers topk:5 topk:32 entropy:16,80 --rollouts 8 \
  --seeds 0 1 2 3 4 --max-scenarios 8 --easy-hard-quantile 0.25 --threads 1 --out runs/ablate_s51
for spec in "reward-or reward.kind=or" "reward-apr reward.kind=apr" "reward-ahr reward.kind=ahr" "reward-shr reward.kind=shr"; do key=${spec%% *}
  [ -f $T/$key/final/model.safetensors ] || r1sim finetune --config configs/grpo_s45_slow01.yaml --set ${spec#* } max_iters=15 keep_every=0 out_dir=$T/$key
done
r1sim ablate --data data/generated/default/test --il $IL --grpo $T/grpo/final \
  --reward-ckpt or=$T/reward-or/final apr=$T/reward-apr/final ahr=$T/reward-ahr/final shr=$T/reward-shr/final \
  --rewards or apr ahr spr shr --samplers entropy:16,80 --rollouts 8 --seeds 0 1 2 3 4 --max-scenarios 8 \
  --easy-hard-quantile 0.25 --threads 1 --out runs/ablate_s51_rewards
echo DONE
