#!/bin/bash
# session 54: GRPO candidates vs the pretrained start on the VALIDATION split (checkpoint choice), top-5, 8 scenes, seeds 0-4
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
V=data/generated/default/val
E="python scripts/eval_grpo_vs_pretrained.py --pretrained runs/s45_slow01/final --sampler topk:5 --threads 1 --data $V"
$E --grpo docs/training/runs/grpo_s52_nano_top5/final_it40 --out docs/eval_s54/val_nano40.json > runs/evalA54_nano40.log 2>&1
for c in 4 8 12; do
  $E --grpo runs/grpo_s54_default/ckpt-$(printf %06d $c) --reuse-pretrained docs/eval_s54/val_nano40.json --out docs/eval_s54/val_default_$c.json > runs/evalA54_default_$c.log 2>&1
done

