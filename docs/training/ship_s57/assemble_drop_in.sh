#!/bin/bash
# Session 57: docs/simulate's seed-0 report for the shipped r1sim-nano (grpo_s56_ph_only @ 24), assembled from the
# session-56 runs of the same weights (same SHA-256; runs listed in docs/training/grpo_s56/README.md, "Every mode at
# seed 0"), collected with `--reuse` for every policy mode (native rerun: same seed and demand, so the same summary, plus
# its time-space samples for the pictures' first panel), then copied into docs/simulate (report, per-mode JSONs and
# time-space pictures). Rerunning every mode from scratch instead:
#   bash docs/simulate/candidate_s55/run_ship_drop_in.sh   (33 min on one thread; same runs, same figures)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
S=runs/s56_only_24; O=runs/ship57_nano_s0; mkdir -p $O
[ -d $S/full_s0 ] || { echo "$S/full_s0 missing: run docs/simulate/candidate_s55/run_ship_drop_in.sh instead"; exit 1; }
cp $S/full_s0/*.json $O/
for d in commands_all position position_rest missing_a missing_b; do cp $S/$d/*_*.time_space.png $O/ 2>/dev/null; done
rm -f $O/*_native.json   # native reruns in seconds and draws its own time-space samples (the first panel)
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw \
  --reuse commands position position-raw > $O.log 2>&1 || { tail $O.log; exit 1; }
cp $O/report.md $O/report.json $O/*_native.json $O/*_native.time_space.png $O/*_commands.json $O/*_commands.time_space.png $O/*_position.json $O/*_position.time_space.png \
   $O/*_position-raw.json $O/*_position-raw.time_space.png $O/*_time_space.png docs/simulate/
