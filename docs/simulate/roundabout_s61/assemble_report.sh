#!/bin/bash
# Session 61: docs/simulate's seed-0 report with the position drive of session 61 (SUMO drives the turns off the major
# road; the yield rule on SUMO's isOpen), assembled with `--reuse`: native, commands and position-raw are session 60's
# rows (runs/ship60_s0; neither change reaches the commands drive or the raw position drive: both are in the safety
# layer of the position drive), position from this session's runs of commits e87cea4 and deb7ff0 (game/cross rerun: its turns are signalised)
# (runs/turn61_s0: `bash docs/simulate/roundabout_s61/run_position.sh 0`; the same rows at deb7ff0 except game/cross).
# Rerunning every mode from scratch gives the same rows:
#   python examples/full_horizon_runs.py --out OUT --seed 0 --modes native commands position position-raw   (~35 min)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
O=runs/ship61_s0; mkdir -p $O
cp runs/ship60_s0/*.json $O/
cp runs/turn61_s0/*_position.* $O/
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw \
  --reuse native commands position position-raw > $O.log 2>&1 || { tail $O.log; exit 1; }
mkdir -p docs/simulate/previous_s60 && cp docs/simulate/report.md docs/simulate/report.json docs/simulate/previous_s60/
cp $O/report.md $O/report.json $O/*.json $O/*.time_space.png $O/*_time_space.png docs/simulate/
rm -f docs/simulate/*.time_space.samples.json
