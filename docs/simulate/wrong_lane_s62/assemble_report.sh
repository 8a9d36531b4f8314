#!/bin/bash
# Session 62: docs/simulate's seed-0 report with the position drive of session 62 (a vehicle in a lane that does not
# continue its route is SUMO's within SUMO's strategic look-ahead, 10 s x its allowed speed), assembled with `--reuse`:
# native and commands are session 60's rows (runs/ship61_s0; the change is in the position drive's checks only),
# position and position-raw from this session's run of commit 8c5dbb3 (runs/wl62pkg_s0:
# `bash docs/simulate/wrong_lane_s62/run_position.sh 0 raw`; the raw drive has the same hand-over).
# Rerunning every mode from scratch gives the same rows:
#   python examples/full_horizon_runs.py --out OUT --seed 0 --modes native commands position position-raw   (~35 min)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
O=runs/ship62_s0; mkdir -p $O
cp runs/ship61_s0/*.json $O/
cp runs/wl62pkg_s0/*_position.* runs/wl62pkg_s0/*_position-raw.* $O/
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw \
  --reuse native commands position position-raw > $O.log 2>&1 || { tail $O.log; exit 1; }
mkdir -p docs/simulate/previous_s61 && cp docs/simulate/report.md docs/simulate/report.json docs/simulate/previous_s61/
cp $O/report.md $O/report.json $O/*.json $O/*.time_space.png $O/*_time_space.png docs/simulate/
rm -f docs/simulate/*.time_space.samples.json
