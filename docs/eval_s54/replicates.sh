#!/bin/bash
# usage: bash docs/eval_s54/replicates.sh CKPT LABEL -- session 54: CKPT vs the pretrained start s45_slow01 under top-5 on
# the test split (the issue's 8 scenes and seeds 0-4, seeds 5-9, 24 scenes x seeds 0-2) and the validation split (seeds
# 5-9, 24 scenes x seeds 0-2), the start's side reused from earlier outputs; writes docs/eval_s54/{test,val}_LABEL*.json.
# Run as: replicates.sh runs/grpo_s54_shr/ckpt-000012 shr_12 (evalF) and replicates.sh runs/grpo_s54_shr_24/ckpt-000016 shr_16 (evalH).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
G=${1:?checkpoint}; L=${2:?label}
E="python scripts/eval_grpo_vs_pretrained.py --pretrained runs/s45_slow01/final --sampler topk:5 --threads 1 --grpo $G"
V=data/generated/default/val
( $E --reuse-pretrained docs/eval_grpo_s52_nano_top5_40_vs_s45_slow01.json --out docs/eval_s54/test_$L.json
  $E --seeds 0 1 2 --num-scenes 24 --reuse-pretrained docs/eval_grpo_s53_nano_24scenes_vs_s45_slow01.json --out docs/eval_s54/test_${L}_24scenes.json
  $E --data $V --seeds 5 6 7 8 9 --reuse-pretrained docs/eval_s54/val_nano40_seeds5to9.json --out docs/eval_s54/val_${L}_seeds5to9.json ) &
$E --seeds 5 6 7 8 9 --reuse-pretrained docs/eval_grpo_s53_nano_seeds5to9_vs_s45_slow01.json --out docs/eval_s54/test_${L}_seeds5to9.json
$E --data $V --seeds 0 1 2 --num-scenes 24 --reuse-pretrained docs/eval_s54/val_nano40_24scenes.json --out docs/eval_s54/val_${L}_24scenes.json
wait
