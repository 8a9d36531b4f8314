#!/bin/bash
# Session 60: docs/simulate's seed-0 report with the position drive's junction_turns="sumo", assembled with `--reuse`:
# native, commands and position-raw rerun this session (`python examples/full_horizon_runs.py --out runs/ship60_s0
# --seed 0 --modes native commands position-raw`, commit 5c26393: the same rows as session 59's report, bit for bit --
# the commands drive moves no vehicle and the raw position drive has no safety layer, so the change reaches neither),
# position from this session's run of commit e102ff1 (runs/turn60_s0: `bash docs/simulate/junction_turns_s60/run_position.sh 0`).
# Rerunning every mode from scratch gives the same rows:
#   python examples/full_horizon_runs.py --out OUT --seed 0 --modes native commands position position-raw   (~35 min)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
O=runs/ship60_s0; mkdir -p $O
cp runs/turn60_s0/*_position.* $O/
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw \
  --reuse native commands position position-raw > $O.log 2>&1 || { tail $O.log; exit 1; }
mkdir -p docs/simulate/previous_s59 && cp docs/simulate/report.md docs/simulate/report.json docs/simulate/previous_s59/
cp $O/report.md $O/report.json $O/*.json $O/*.time_space.png $O/*_time_space.png docs/simulate/
rm -f docs/simulate/*.time_space.samples.json
