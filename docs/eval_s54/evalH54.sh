#!/bin/bash
# session 54: replicates and card of grpo_s54_shr @ 16 (best of @ 4-24 on val seeds 0-4)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
G=runs/grpo_s54_shr_24/ckpt-000016
E="python scripts/eval_grpo_vs_pretrained.py --pretrained runs/s45_slow01/final --sampler topk:5 --threads 1 --grpo $G"
V=data/generated/default/val
( $E --reuse-pretrained docs/eval_grpo_s52_nano_top5_40_vs_s45_slow01.json --out docs/eval_s54/test_shr_16.json > runs/evalH54_test.log 2>&1
  $E --seeds 0 1 2 --num-scenes 24 --reuse-pretrained docs/eval_grpo_s53_nano_24scenes_vs_s45_slow01.json --out docs/eval_s54/test_shr_16_24scenes.json > runs/evalH54_test24.log 2>&1
  $E --data $V --seeds 5 6 7 8 9 --reuse-pretrained docs/eval_s54/val_nano40_seeds5to9.json --out docs/eval_s54/val_shr_16_seeds5to9.json > runs/evalH54_val59.log 2>&1 ) &
python -m r1sim_sumo.train.model_card runs/cards54/shr16 --train data/generated/default/train --heldout data/generated/default/val --closed-loop data/generated/default/test --max-heldout 400 --max-closed-loop 40 --rollouts 8 --sampler topk:5 --threads 1 > runs/cards54/shr16.log 2>&1
$E --seeds 5 6 7 8 9 --reuse-pretrained docs/eval_grpo_s53_nano_seeds5to9_vs_s45_slow01.json --out docs/eval_s54/test_shr_16_seeds5to9.json > runs/evalH54_test59.log 2>&1
$E --data $V --seeds 0 1 2 --num-scenes 24 --reuse-pretrained docs/eval_s54/val_nano40_24scenes.json --out docs/eval_s54/val_shr_16_24scenes.json > runs/evalH54_val24.log 2>&1
wait

