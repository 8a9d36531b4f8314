#!/usr/bin/env bash
# Two GRPO runs side by side on one lent GPU machine (the `device` tool's `run`): scripts/device_grpo.sh once per
# config, each with its own probe folder and its own $OUT/<name>/ (final.tar, KEEP checkpoint tars, the training
# state in 15 MiB parts; the tool brings back 8 files, so KEEP=2 for two runs: in session 58 the packing took every
# kept checkpoint, 10 files came, and one run's final.tar and state were left out; it packs the newest KEEP now). A small model leaves the GPU mostly
# idle, so two runs side by side cost little more device time than one. Before the `run`, here:
#   bash scripts/device_slim_tree.sh slim     # docs/ etc. leave the index (they do not travel); `restore` after
# and the `run` (carry: the configs' train_tokens folders and .whl with a shapely wheel for the machine's Python 3.12):
#   python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
#     && export PYTHONPATH=/tmp/site; CONFIGS="configs/a.yaml configs/b.yaml" BUDGET_S=450 bash scripts/device_two_grpo.sh
# Back here, per run X (folder $OUT/X, X the config's file name without .yaml): as in scripts/device_grpo.sh's header.
set -u
CONFIGS=${CONFIGS:?name two fine-tuning configs, e.g. CONFIGS="configs/a.yaml configs/b.yaml"}
BUDGET_S=${BUDGET_S:-450}
KEEP=${KEEP:-2}
ROOT_OUT=${OUT:-/tmp/device_out}
pids=()
for c in $CONFIGS; do
  name=$(basename "$c" .yaml)
  mkdir -p "$ROOT_OUT/$name"
  OUT="$ROOT_OUT/$name" PROBE_DIR="/tmp/probe_$name" CONFIG="$c" BUDGET_S="$BUDGET_S" KEEP="$KEEP" \
    PROBE_ITERS=${PROBE_ITERS:-2} bash scripts/device_grpo.sh > "/tmp/$name.driver.log" 2>&1 &
  pids+=($!)
done
rc=0
for p in "${pids[@]}"; do wait "$p" || rc=$?; done
for c in $CONFIGS; do name=$(basename "$c" .yaml); echo "=== $name"; tail -n 12 "/tmp/$name.driver.log"; done
exit $rc
