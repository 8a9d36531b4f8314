#!/bin/bash
# Session 58: docs/simulate's seed-0 report with the drop-in's new default (speed carry `gains` in both drives, `off` in
# the position drive without the safety layer), assembled with `--reuse` from runs of the same weights and seed:
# native and position-raw from session 57's (runs/ship57_nano_s0: the raw default did not change), commands and
# position from this session's `--speed-carry gains` runs (runs/carry_s58/{cmd_a,cmd_b,mm_gains,ramp_gains,gains_a,gains_b},
# commands in docs/simulate/speed_carry_s58/README.md). Rerunning every mode from scratch gives the same rows:
#   python examples/full_horizon_runs.py --out OUT --seed 0 --modes native commands position position-raw   (~35 min)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
O=runs/ship58_s0; mkdir -p $O
cp runs/ship57_nano_s0/*_native.* runs/ship57_nano_s0/*_position-raw.* $O/
for d in cmd_a cmd_b; do cp runs/carry_s58/$d/*_commands.* $O/; done
for d in mm_gains ramp_gains gains_a gains_b; do cp runs/carry_s58/$d/*_position.* $O/; done
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw \
  --reuse native commands position position-raw > $O.log 2>&1 || { tail $O.log; exit 1; }
mkdir -p docs/simulate/previous_carry_off_s57 && cp docs/simulate/report.md docs/simulate/report.json docs/simulate/previous_carry_off_s57/
cp $O/report.md $O/report.json $O/*_commands.json $O/*_commands.time_space.png $O/*_position.json $O/*_position.time_space.png \
   $O/*_time_space.png docs/simulate/
