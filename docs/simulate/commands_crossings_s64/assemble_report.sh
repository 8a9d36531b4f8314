#!/bin/bash
# Session 64: docs/simulate's seed-0 report with the commands drive's new default (SUMO drives the speed through each
# junction where the vehicle may have to stop, `--junction-crossings sumo`; policy_vkm_share without the distance SUMO
# drove), assembled with `--reuse`: native rows as in session 63 (runs/ship63_s0), commands from this session's run at
# commit b715b35 (runs/ship64_s0: `python examples/full_horizon_runs.py --scenarios <all 8> --modes native commands
# --reuse native --seed 0 --out runs/ship64_s0`, native copied in first), position and position-raw session 63's rows
# (the position drive did not change). Rerunning every mode from scratch gives the same rows:
#   python examples/full_horizon_runs.py --out OUT --seed 0 --modes native commands position position-raw   (~35 min)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
O=runs/ship64_s0; mkdir -p $O
cp runs/ship63_s0/*_position.* runs/ship63_s0/*_position-raw.* $O/
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw \
  --reuse native commands position position-raw > $O.rebuild.log 2>&1 || { tail $O.rebuild.log; exit 1; }
mkdir -p docs/simulate/previous_s63 && cp docs/simulate/report.md docs/simulate/report.json docs/simulate/previous_s63/
cp $O/report.md $O/report.json $O/*.json $O/*.time_space.png $O/*_time_space.png docs/simulate/
rm -f docs/simulate/*.time_space.samples.json
