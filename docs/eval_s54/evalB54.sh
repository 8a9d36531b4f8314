#!/bin/bash
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
# needs runs/s45_slow01/final (docs/training/README.md section 4) and the checkpoints named below; run evalA54.sh first (the start's side is reused from its output)
export OMP_NUM_THREADS=1
V=data/generated/default/val
E="python scripts/eval_grpo_vs_pretrained.py --pretrained runs/s45_slow01/final --sampler topk:5 --threads 1 --data $V"
for c in 4 8 12; do
  $E --grpo runs/grpo_s54_mix/ckpt-$(printf %06d $c) --reuse-pretrained docs/eval_s54/val_nano40.json --out docs/eval_s54/val_mix_$c.json > runs/evalB54_mix_$c.log 2>&1
done

