#!/bin/bash
# usage: bash docs/training/run_card_copy_s51.sh LABEL CKPT [ROLLOUTS] -- the nano's model-card command on a copy in runs/cards/LABEL[_rR]
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
L=$1; C=$2; R=${3:-8}
export OMP_NUM_THREADS=1
D=runs/cards/$L; [ "$R" != 8 ] && D=${D}_r$R
rm -rf $D && mkdir -p runs/cards && cp -r $C $D
python -m r1sim_sumo.train.model_card $D --train data/generated/default/train --heldout data/generated/default/val \
  --closed-loop data/generated/default/test --max-heldout 400 --max-closed-loop 40 --rollouts $R --sampler topk:5 --threads 1 \
  > $D.log 2>&1
touch $D.done
