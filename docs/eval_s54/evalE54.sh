#!/bin/bash
# session 54: gated / shr reward continuations vs the pretrained start on the validation split
# usage: bash docs/eval_s54/evalE54.sh gated|shr (after r1sim finetune --config configs/grpo_s54_<that>.yaml)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
V=data/generated/default/val
E="python scripts/eval_grpo_vs_pretrained.py --pretrained runs/s45_slow01/final --sampler topk:5 --threads 1 --data $V --reuse-pretrained docs/eval_s54/val_nano40.json"
r=$1
for c in 4 8 12; do
  ck=runs/grpo_s54_$r/ckpt-$(printf %06d $c)
  $E --grpo $ck --out docs/eval_s54/val_${r}_$c.json > runs/evalE54_${r}_$c.log 2>&1
done

