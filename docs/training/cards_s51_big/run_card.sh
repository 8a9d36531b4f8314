#!/bin/bash
# usage: bash docs/training/cards_s51_big/run_card.sh LABEL CKPT -- the card command with 4x the closed-loop scenes (--max-closed-loop 160), held-out NLL on 50 scenes
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
L=$1; C=$2
export OMP_NUM_THREADS=1
D=runs/cards/big_$L; rm -rf $D && mkdir -p runs/cards && cp -r $C $D
python -m r1sim_sumo.train.model_card $D --train data/generated/default/train --heldout data/generated/default/val \
  --closed-loop data/generated/default/test --max-heldout 50 --max-closed-loop 160 --rollouts 8 --sampler topk:5 --threads 1 > $D.log 2>&1
touch $D.done
