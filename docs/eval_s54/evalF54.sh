#!/bin/bash
# session 54: replicates of grpo_s54_shr @ 12 (test split: the issue's scenes and seeds, seeds 5-9, 24 scenes; val: seeds 5-9, 24 scenes)
# needs runs/s45_slow01/final and runs/grpo_s54_shr (r1sim finetune --config configs/grpo_s54_shr.yaml, or its weights in docs/training/runs/grpo_s54_shr/final_it12)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
G=runs/grpo_s54_shr/ckpt-000012
E="python scripts/eval_grpo_vs_pretrained.py --pretrained runs/s45_slow01/final --sampler topk:5 --threads 1 --grpo $G"
V=data/generated/default/val
( $E --reuse-pretrained docs/eval_grpo_s52_nano_top5_40_vs_s45_slow01.json --out docs/eval_s54/test_shr_12.json > runs/evalF54_test.log 2>&1
  $E --seeds 5 6 7 8 9 --reuse-pretrained docs/eval_grpo_s53_nano_seeds5to9_vs_s45_slow01.json --out docs/eval_s54/test_shr_12_seeds5to9.json > runs/evalF54_test59.log 2>&1
  $E --data $V --seeds 5 6 7 8 9 --reuse-pretrained docs/eval_s54/val_nano40_seeds5to9.json --out docs/eval_s54/val_shr_12_seeds5to9.json > runs/evalF54_val59.log 2>&1 ) &
$E --seeds 0 1 2 --num-scenes 24 --reuse-pretrained docs/eval_grpo_s53_nano_24scenes_vs_s45_slow01.json --out docs/eval_s54/test_shr_12_24scenes.json > runs/evalF54_test24.log 2>&1
$E --data $V --seeds 0 1 2 --num-scenes 24 --reuse-pretrained docs/eval_s54/val_nano40_24scenes.json --out docs/eval_s54/val_shr_12_24scenes.json > runs/evalF54_val24.log 2>&1
wait

