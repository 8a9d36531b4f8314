#!/bin/bash
# Session 65: docs/simulate's seed-0 report with the position drive's along-lane rules (frames held by the lane-change
# gate or moved back from over the carriageway's left edge point along their lane; a vehicle turning against its lane
# is handed back, `against_lane`), assembled with `--reuse`: native, commands and position-raw rows as in session 64
# (runs/ship64_s0; the rules act only in the position drive with the safety layer), position from this session's run of
# the package (runs/s65e_s0, run.sh). Rerunning every mode from scratch gives the same rows:
#   python examples/full_horizon_runs.py --out OUT --seed 0 --modes native commands position position-raw   (~35 min)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
O=runs/ship65_s0; mkdir -p $O
cp runs/ship64_s0/* $O/
cp runs/ship63_s0/*_native.time_space.samples.json $O/  # native's samples: session 64's report lost the pictures' native panel
cp runs/s65e_s0/*_position.* $O/
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw \
  --reuse native commands position position-raw > $O.rebuild.log 2>&1 || { tail $O.rebuild.log; exit 1; }
[ -d docs/simulate/previous_s64 ] || { mkdir -p docs/simulate/previous_s64 && cp docs/simulate/report.md docs/simulate/report.json docs/simulate/previous_s64/; }
cp $O/report.md $O/report.json $O/*.json $O/*.time_space.png $O/*_time_space.png docs/simulate/
rm -f docs/simulate/*.time_space.samples.json
