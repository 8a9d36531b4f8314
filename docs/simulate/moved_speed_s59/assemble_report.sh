#!/bin/bash
# Session 59: docs/simulate's seed-0 report with the position drive's session-59 fixes (plans from the speed each
# vehicle was moved at, standing vehicles over the centre line snapped back, unlocated plan frames kept on the
# carriageway), assembled with `--reuse` from runs of the same weights and seed: native and commands from session 58's
# (runs/ship58_s0: the commands drive moves no vehicle, so nothing changed for it), position and position-raw from this
# session's runs of commit a246aa0 (runs/snap59_s0, runs/snapraw59_s0: `bash docs/simulate/moved_speed_s59/run_position.sh 0`
# and `python examples/full_horizon_runs.py --out runs/snapraw59_s0 --seed 0 --modes native position-raw`).
# Rerunning every mode from scratch gives the same rows:
#   python examples/full_horizon_runs.py --out OUT --seed 0 --modes native commands position position-raw   (~35 min)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
O=runs/ship59_s0; mkdir -p $O
cp runs/ship58_s0/*_native.* runs/ship58_s0/*_commands.* $O/
cp runs/snap59_s0/*_position.* $O/
cp runs/snapraw59_s0/*_position-raw.* $O/
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw \
  --reuse native commands position position-raw > $O.log 2>&1 || { tail $O.log; exit 1; }
mkdir -p docs/simulate/previous_s58 && cp docs/simulate/report.md docs/simulate/report.json docs/simulate/previous_s58/
cp $O/report.md $O/report.json $O/*_position.json $O/*_position.time_space.png $O/*_position-raw.json \
   $O/*_position-raw.time_space.png $O/*_time_space.png docs/simulate/
