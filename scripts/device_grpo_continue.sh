#!/usr/bin/env bash
# Continue GRPO runs side by side on a lent GPU machine (the `device` tool's `run`) for a fixed wall time, from the
# training state (weights + AdamW) they left: `r1sim finetune --resume` under `timeout BUDGET_S`, a state every 2
# iterations, a kept checkpoint every KEEP_EVERY. What each run reached comes back in $OUT (the tool returns at most 8
# files): <name>.tar (log.csv, config.yaml, state.json, train.log and the newest two kept checkpoints) and
# <name>.state.safetensors (9.1 MiB for the nano's size); gpu.txt holds the GPU's use.
# The runs travel as their state alone: here, before the `run`,
#   bash scripts/device_slim_tree.sh slim
#   mkdir -p dev64 && echo /dev64/ >> .git/info/exclude && for r in runs/A runs/B; do mkdir -p dev64/$(basename $r) &&
#     cp -r $r/state $r/config.yaml $r/log.csv dev64/$(basename $r)/; done
# then the `run` with carry [the configs' train_tokens folders, .whl (shapely for the offroad reward), dev64]:
#   python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
#     && export PYTHONPATH=/tmp/site; RUNS="grpo_gpu_s58_ph grpo_gpu_s58_ph_speedup_k32" BUDGET_S=540 \
#     bash scripts/device_grpo_continue.sh
# Back here, per run X: tar xf X.tar -C runs/X && cp X.state.safetensors runs/X/state/state.safetensors &&
#   mv runs/X/state.json runs/X/state/ ; then `r1sim finetune --config runs/X/config.yaml --resume --set device=cpu
#   max_iters=<reached>` writes runs/X/final here (or continues it).
set -u
RUNS=${RUNS:?name the run folders of dev64/ to continue, e.g. RUNS="grpo_gpu_s58_ph"}
BUDGET_S=${BUDGET_S:-540}
KEEP_EVERY=${KEEP_EVERY:-6}
SRC=${SRC:-dev64}
OUT=${OUT:-/tmp/device_out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} R1SIM_NO_PROGRESS=1
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>&1 | tee "$OUT/gpu.txt"
( while sleep 15; do nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader >> "$OUT/gpu.txt" 2>&1; done ) &
WATCH=$!
pids=()
for name in $RUNS; do
  # a fresh device tree has no runs/ (ignored, not carried): never overwrite a run folder that is already there
  if [ -e "runs/$name" ]; then echo "runs/$name exists: move it away first (this script copies $SRC/$name there)"; exit 1; fi
  mkdir -p runs && cp -r "$SRC/$name" "runs/$name"
  timeout "$BUDGET_S" python3 -m r1sim_sumo.cli finetune --config "runs/$name/config.yaml" --resume \
    --set max_iters=400 ckpt_every=2 keep_every="$KEEP_EVERY" ${EXTRA_SET:-} > "runs/$name/train.log" 2>&1 &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; echo "finetune exit status $? (124: stopped by the budget, as planned)"; done
kill $WATCH 2>/dev/null
for name in $RUNS; do
  echo "=== $name"; grep -v '^\s*$' "runs/$name/train.log" | tail -n 5; tail -n 2 "runs/$name/log.csv" | cut -c1-120
  ( cd "runs/$name" && cp state/state.json . && cp state/state.safetensors "$OUT/$name.state.safetensors" \
    && tar cf "$OUT/$name.tar" log.csv config.yaml state.json train.log $(ls -d ckpt-* 2>/dev/null | sort | tail -n 2) )
done
ls -la "$OUT"
