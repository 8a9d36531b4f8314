#!/bin/bash
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
# grpo_s54_shr resumed from its iteration 12 to 24 (needs runs/grpo_s54_shr from configs/grpo_s54_shr.yaml), then @ 16 / 20 / 24 on val
export OMP_NUM_THREADS=1
cp -r runs/grpo_s54_shr runs/grpo_s54_shr_24
r1sim finetune --config configs/grpo_s54_shr.yaml --resume --set out_dir=runs/grpo_s54_shr_24 max_iters=24 > runs/grpo_s54_shr_24.log 2>&1
V=data/generated/default/val
E="python scripts/eval_grpo_vs_pretrained.py --pretrained runs/s45_slow01/final --sampler topk:5 --threads 1 --data $V --reuse-pretrained docs/eval_s54/val_nano40.json"
for c in 16 20 24; do
  ck=runs/grpo_s54_shr_24/ckpt-$(printf %06d $c)
  $E --grpo $ck --out docs/eval_s54/val_shr_$c.json > runs/evalG54_shr_$c.log 2>&1
done

