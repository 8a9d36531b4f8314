#!/bin/bash
# session 54: the nano's GRPO lineage vs the pretrained start on the validation split (top-5, 8 scenes, seeds 0-4)
# needs runs/s45_slow01/final (docs/training/README.md section 4) and the checkpoints named below; run evalA54.sh first (the start's side is reused from its output)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
V=data/generated/default/val
E="python scripts/eval_grpo_vs_pretrained.py --pretrained runs/s45_slow01/final --sampler topk:5 --threads 1 --data $V --reuse-pretrained docs/eval_s54/val_nano40.json"
run() { $E --grpo $1 --out docs/eval_s54/val_$2.json > runs/evalD54_$2.log 2>&1; }
(run runs/grpo_s45_slow01/final s45_30; run runs/grpo_s51_nudge/ckpt-000010 s51_nudge10; run runs/grpo_s52_nano_top5/ckpt-000020 s52_20; run runs/grpo_s52_nano_top5_60/ckpt-000050 s52_50) &
(run runs/grpo_s46_lr1e4/final s46_lr1e4; run runs/grpo_s52_nano_top5/ckpt-000010 s52_10; run runs/grpo_s52_nano_top5/ckpt-000030 s52_30; run runs/grpo_s52_nano_top5_60/ckpt-000060 s52_60)
wait

