#!/bin/bash
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
# needs runs/s45_slow01/final (docs/training/README.md section 4) and the checkpoints named below
export OMP_NUM_THREADS=1
V=data/generated/default/val
E="python scripts/eval_grpo_vs_pretrained.py --pretrained runs/s45_slow01/final --sampler topk:5 --threads 1 --data $V --grpo docs/training/runs/grpo_s52_nano_top5/final_it40"
$E --seeds 5 6 7 8 9 --out docs/eval_s54/val_nano40_seeds5to9.json > runs/evalC54_a.log 2>&1 &
$E --seeds 0 1 2 --num-scenes 24 --out docs/eval_s54/val_nano40_24scenes.json > runs/evalC54_b.log 2>&1
wait

