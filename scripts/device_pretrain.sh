#!/usr/bin/env bash
# One pretraining segment on a lent GPU machine (the `device` tool's `run`), its results packed into $OUT so that they
# come back (at most 8 files of 16 MiB): the run folder without its state and kept checkpoints as final.tar, each kept
# checkpoint as its own tar, the training state (weights +
# AdamW, ~16 MiB) split in 15 MiB parts, the log. Needs the config's token data and init checkpoint carried along.
# The tracked tree is far over the tool's 64 MiB: first `bash scripts/device_slim_tree.sh slim` here (the big folders
# leave the index, not the disk), then the `run` with carry [data/tokens/ext, data/tokens/rings_ext], then `restore`.
# Keep at most 8 files in $OUT: keep_every no smaller than max_steps / 2.
#   CONFIG=configs/campaign_gpu_ext.yaml BUDGET_S=520 bash scripts/device_pretrain.sh
# Back here: mkdir -p runs/X && tar xf final.tar -C runs/X && mkdir -p runs/X/state && cat state.part.* >
# runs/X/state/state.safetensors (state.json is in final.tar); then `r1sim pretrain --config runs/X/config.yaml --resume`.
set -u
CONFIG=${CONFIG:-configs/campaign_gpu_ext.yaml}
BUDGET_S=${BUDGET_S:-520}
OUT=${OUT:-/tmp/device_out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
RUN=$(python3 -c "import yaml,sys; print(yaml.safe_load(open('$CONFIG'))['out_dir'])")
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee "$OUT/gpu.txt"
( while sleep 15; do nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader >> "$OUT/gpu.txt"; done ) &
WATCH=$!
RESUME=""; [ -f "$RUN/state/state.safetensors" ] && RESUME="--resume"
timeout "$BUDGET_S" python3 -m r1sim_sumo.cli pretrain --config "$CONFIG" $RESUME > "$OUT/train.log" 2>&1
echo "pretrain exit status $?"
kill $WATCH 2>/dev/null
tr '\r' '\n' < "$OUT/train.log" | grep -v '^pretrain:' | tail -n 40
tail -n 3 "$RUN/log.csv"
( cd "$RUN" && tar cf "$OUT/final.tar" --exclude=state.safetensors --exclude='ckpt-*' . \
  && for c in ckpt-*; do [ -d "$c" ] && tar cf "$OUT/$c.tar" "$c"; done; split -b 15m state/state.safetensors "$OUT/state.part." )
ls -la "$OUT"
