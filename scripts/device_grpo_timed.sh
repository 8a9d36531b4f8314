#!/usr/bin/env bash
# One GRPO run on a lent GPU machine for a fixed wall time, no probe (scripts/device_grpo.sh probes first, which costs
# a start-up twice): `timeout BUDGET_S` on a run with a large max_iters and a checkpoint every 2 iterations; what it
# reached comes back in $OUT: the newest checkpoint (tar) and the training state in 15 MiB parts (continue or write
# final weights here with `r1sim finetune --config runs/X/config.yaml --resume --set device=cpu max_iters=<reached>`).
#   CONFIG=configs/x.yaml BUDGET_S=200 bash scripts/device_grpo_timed.sh
set -u
CONFIG=${CONFIG:?name the fine-tuning config}
BUDGET_S=${BUDGET_S:-200}
OUT=${OUT:-/tmp/device_out}
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} R1SIM_NO_PROGRESS=1
RUN=$(python3 -c "import sys, yaml; print(yaml.safe_load(open(sys.argv[1]))['out_dir'])" "$CONFIG")
timeout "$BUDGET_S" python3 -m r1sim_sumo.cli finetune --config "$CONFIG" --set max_iters=400 ckpt_every=2 keep_every=2 \
  > "$OUT/train.log" 2>&1
echo "finetune exit status $? after ${BUDGET_S} s at most"
tail -n 4 "$RUN/log.csv"
cp "$RUN/log.csv" "$RUN/config.yaml" "$OUT/" 2>/dev/null
( cd "$RUN" && c=$(ls -d ckpt-* 2>/dev/null | sort | tail -n 1) && [ -n "$c" ] && tar cf "$OUT/$c.tar" "$c" && cp state/state.json "$OUT/" \
  && split -b 15m state/state.safetensors "$OUT/state.part." )
ls -la "$OUT"
