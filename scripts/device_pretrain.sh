#!/usr/bin/env bash
# One pretraining segment on a lent GPU machine (the `device` tool's `run`), its results packed into $OUT so that they
# come back (at most 8 files of 16 MiB): the run folder without its state and kept checkpoints as final.tar, each kept
# checkpoint as its own tar, the training state (weights +
# AdamW, ~16 MiB) split in 15 MiB parts, the log. Needs the config's token data and init checkpoint carried along.
# The tracked tree is far over the tool's 64 MiB: first `bash scripts/device_slim_tree.sh slim` here (the big folders
# leave the index, not the disk), then the `run` with carry [data/tokens/ext, data/tokens/rings_ext], then `restore`.
# Keep at most 8 files in $OUT: keep_every no smaller than max_steps / 2.
#   CONFIG=configs/campaign_gpu_ext.yaml BUDGET_S=520 bash scripts/device_pretrain.sh
# PROBE_STEPS=N first times N steps (into /tmp, thrown away) and sets max_steps so that the whole schedule (its cosine
# decay included) ends inside what is left of BUDGET_S; the config's max_steps is the upper bound.
# A wider model's state and final weights together can pass the 64 MiB that come back: then final/model.safetensors
# stays behind and is rebuilt here from the state (`python scripts/checkpoint_from_state.py runs/X --like
# <any checkpoint of the same config> --out runs/X/final_rebuilt`).
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
SET=()
if [ -n "${PROBE_STEPS:-}" ]; then
  T0=$(date +%s)
  python3 -m r1sim_sumo.cli pretrain --config "$CONFIG" --set max_steps="$PROBE_STEPS" log_every=5 ckpt_every=100000 \
    keep_every=0 out_dir=/tmp/probe_run > "$OUT/probe.log" 2>&1
  STEPS=$(python3 - "$CONFIG" "$PROBE_STEPS" "$BUDGET_S" "$(( $(date +%s) - T0 ))" <<'PY'
import csv, sys, yaml
cfg, n, budget, spent = yaml.safe_load(open(sys.argv[1])), int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
rows = list(csv.DictReader(open("/tmp/probe_run/log.csv")))
a, b = rows[1], rows[-2]  # skip the first rows (warm-up, compilation) and the last (with its evaluation)
per_step = (float(b["wall_s"]) - float(a["wall_s"])) / (int(b["step"]) - int(a["step"]))
first = float(rows[0]["wall_s"])  # start-up to the first logged step (data loading, workers)
left = budget - spent - first - 30.0  # 30 s for evaluations, checkpoints and packing
steps = max(1, min(int(cfg["max_steps"]), int(0.9 * left / per_step)))
print(steps)
print(f"probe: {per_step:.3f} s/step, start-up {first:.0f} s, probe took {spent:.0f} s -> max_steps {steps}", file=sys.stderr)
PY
)
  SET=(--set max_steps="$STEPS")
  BUDGET_S=$(( BUDGET_S - ( $(date +%s) - T0 ) ))
fi
timeout "$BUDGET_S" python3 -m r1sim_sumo.cli pretrain --config "$CONFIG" $RESUME "${SET[@]}" > "$OUT/train.log" 2>&1
echo "pretrain exit status $?"
kill $WATCH 2>/dev/null
tr '\r' '\n' < "$OUT/train.log" | grep -v '^pretrain:' | tail -n 40
tail -n 3 "$RUN/log.csv"
BIG=(); [ "$(du -cm "$RUN/state/state.safetensors" "$RUN/final/model.safetensors" 2>/dev/null | tail -1 | cut -f1)" -gt 56 ] \
  && BIG=(--exclude=final/model.safetensors) && echo "final/model.safetensors stays behind: rebuild it from the state"
( cd "$RUN" && tar cf "$OUT/final.tar" --exclude=state.safetensors --exclude='ckpt-*' "${BIG[@]}" . \
  && for c in ckpt-*; do [ -d "$c" ] && tar cf "$OUT/$c.tar" "$c"; done; split -b 15m state/state.safetensors "$OUT/state.part." )
ls -la "$OUT"
