#!/usr/bin/env bash
# One GRPO fine-tuning run on a lent GPU machine (the `device` tool's `run`), its results packed into $OUT so that they
# come back (at most 8 files of 16 MiB): final.tar (the run folder without its training state and kept checkpoints:
# final weights, config, log, GPU use), each kept checkpoint as its own tar, the training state (weights + AdamW) in
# 15 MiB parts. Rollouts, rewards and updates run on the GPU (GRPOConfig.device: cuda); the scenes come from compact
# token datasets (GRPOConfig.train_tokens), which fit in what travels where scenario datasets do not.
#
# First a probe: PROBE_ITERS iterations into /tmp (thrown away) check the device path end to end and time an
# iteration; then max_iters is set so that the run ends inside BUDGET_S (the config's max_iters is the upper bound)
# and the newest KEEP checkpoints come back (the tool returns at most 8 files: final.tar, the state parts, KEEP tars).
# The tracked tree is far over the tool's 64 MiB: here first
# `bash scripts/device_slim_tree.sh slim` (docs/ leaves the index, not the disk), copy the init checkpoint into runs/,
# then the `run` with carry [the config's train_tokens folders, runs/<init>], then `restore`:
#   CONFIG=configs/grpo_gpu_s38.yaml INIT=runs/init_s34_rec_long BUDGET_S=480 bash scripts/device_grpo.sh
# Back here: mkdir -p runs/X && tar xf final.tar -C runs/X && for t in ckpt-*.tar; do tar xf $t -C runs/X; done &&
# mkdir -p runs/X/state && cat state.part.* > runs/X/state/state.safetensors (state.json is in final.tar); then
# `r1sim finetune --config runs/X/config.yaml --resume --set device=cpu` continues it here (or on a GPU without --set).
set -u
CONFIG=${CONFIG:?name the fine-tuning config, e.g. CONFIG=configs/grpo_gpu_s38.yaml}
BUDGET_S=${BUDGET_S:-480}
PROBE_ITERS=${PROBE_ITERS:-3}
KEEP=${KEEP:-2}
OUT=${OUT:-/tmp/device_out}
PROBE_DIR=${PROBE_DIR:-/tmp/grpo_probe}  # two runs side by side need two
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} R1SIM_NO_PROGRESS=1
T0=$(date +%s)
SET=(${EXTRA_SET:-})  # e.g. EXTRA_SET="device=cpu batch_scenes=2 num_minibatches=4" for a dry run without a GPU
[ -n "${INIT:-}" ] && SET+=(init_checkpoint="$INIT")
RUN=$(python3 - "$CONFIG" "${SET[@]}" <<'PY'
import sys, yaml
out = yaml.safe_load(open(sys.argv[1]))["out_dir"]
for kv in sys.argv[2:]:
    if kv.startswith("out_dir="):
        out = kv.split("=", 1)[1]
print(out)
PY
)
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>&1 | tee "$OUT/gpu.txt"
( while sleep 15; do nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader >> "$OUT/gpu.txt" 2>&1; done ) &
WATCH=$!
python3 -m r1sim_sumo.cli finetune --config "$CONFIG" --set "${SET[@]}" max_iters="$PROBE_ITERS" ckpt_every=100000 \
  keep_every=0 out_dir="$PROBE_DIR" > "$OUT/probe.log" 2>&1
rc=$?
cat "$PROBE_DIR/log.csv" 2>/dev/null
if [ $rc -ne 0 ]; then echo "probe failed (exit $rc):"; tail -n 40 "$OUT/probe.log"; kill $WATCH; exit $rc; fi
ITERS=$(python3 - "$CONFIG" "$BUDGET_S" "$(( $(date +%s) - T0 ))" "$PROBE_DIR" <<'PY'
import csv, sys, yaml
cfg, budget, spent = yaml.safe_load(open(sys.argv[1])), float(sys.argv[2]), float(sys.argv[3])
rows = list(csv.DictReader(open(sys.argv[4] + "/log.csv")))
w = [float(r["wall_s"]) for r in rows]
per_iter = (w[-1] - w[0]) / (len(w) - 1)  # the first iteration holds the warm-up
left = budget - spent - w[0] - 40.0  # start-up as in the probe, 40 s for checkpoints and packing
iters = max(1, min(int(cfg["max_iters"]), int(0.9 * left / per_iter)))
print(iters)
print(f"probe: {per_iter:.2f} s per iteration, first {w[0]:.0f} s, {spent:.0f} s spent -> max_iters {iters}", file=sys.stderr)
PY
)
KEEP_EVERY=$(( ITERS / (KEEP + 1) )); [ "$KEEP_EVERY" -lt 1 ] && KEEP_EVERY=1
LEFT=$(( BUDGET_S - ( $(date +%s) - T0 ) - 20 ))
RESUME=""; [ -f "$RUN/state/state.json" ] && RESUME="--resume"
timeout "$LEFT" python3 -m r1sim_sumo.cli finetune --config "$CONFIG" $RESUME --set "${SET[@]}" max_iters="$ITERS" \
  keep_every="$KEEP_EVERY" > "$OUT/train.log" 2>&1
echo "finetune exit status $? (max_iters $ITERS, keep_every $KEEP_EVERY)"
kill $WATCH 2>/dev/null
tail -n 20 "$OUT/train.log"
tail -n 3 "$RUN/log.csv"
cp "$OUT/gpu.txt" "$OUT/probe.log" "$OUT/train.log" "$RUN/" 2>/dev/null
rm -f "$OUT/gpu.txt" "$OUT/probe.log" "$OUT/train.log"
( cd "$RUN" && tar cf "$OUT/final.tar" --exclude=state.safetensors --exclude='ckpt-*' . \
  && for c in $(ls -d ckpt-* 2>/dev/null | sort | tail -n "$KEEP"); do tar cf "$OUT/$c.tar" "$c"; done; split -b 15m state/state.safetensors "$OUT/state.part." )
ls -la "$OUT"
