#!/bin/bash
# usage: bash docs/training/s52/eval_run.sh LABEL CKPT START -- session 52's evaluation of one GRPO checkpoint on one
# thread: the nano's card command on a copy (37 held-out scenes), the same card on 152 scenes, and the checkpoint
# against its start (scripts/eval_grpo_vs_pretrained.py: 8 held-out scenes x 16 rollouts x 5 seeds, top-5 and
# entropy-guided). Outputs: runs/cards/LABEL, runs/cards/big_LABEL, runs/eval_s52_LABEL.json (+ .done markers).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
L=$1; C=$2; S=$3
export OMP_NUM_THREADS=1
bash docs/training/run_card_copy_s51.sh "$L" "$C"
bash docs/training/cards_s51_big/run_card.sh "$L" "$C"
python scripts/eval_grpo_vs_pretrained.py --pretrained "$S" --grpo "$C" --sampler topk:5 entropy:16,80 --threads 1 \
  --out runs/eval_s52_$L.json > runs/eval_s52_$L.log 2>&1
touch runs/eval_s52_$L.done
