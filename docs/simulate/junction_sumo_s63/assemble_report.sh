#!/bin/bash
# Session 63: docs/simulate's seed-0 report with the position drive of session 63 (SUMO drives a vehicle through each
# junction where it may have to stop, from max(20 m, 3 s x its allowed speed) before the line; taken back once clear
# of the junction), assembled with `--reuse`: native and commands are session 60's rows (runs/ship62_s0; the change is
# in the position drive only), position and position-raw from this session's run of commit 06f0dc0 (runs/jx63pkg_s0:
# `bash docs/simulate/junction_sumo_s63/run_position.sh 0 raw`; the raw drive has the same hand-over).
# Rerunning every mode from scratch gives the same rows:
#   python examples/full_horizon_runs.py --out OUT --seed 0 --modes native commands position position-raw   (~35 min)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
O=runs/ship63_s0; mkdir -p $O
cp runs/ship62_s0/*.json $O/
cp runs/jx63pkg_s0/*_position.* runs/jx63pkg_s0/*_position-raw.* $O/
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw \
  --reuse native commands position position-raw > $O.log 2>&1 || { tail $O.log; exit 1; }
mkdir -p docs/simulate/previous_s62 && cp docs/simulate/report.md docs/simulate/report.json docs/simulate/previous_s62/
cp $O/report.md $O/report.json $O/*.json $O/*.time_space.png $O/*_time_space.png docs/simulate/
rm -f docs/simulate/*.time_space.samples.json
