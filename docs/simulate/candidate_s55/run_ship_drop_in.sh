#!/bin/bash
# usage: bash docs/simulate/candidate_s55/run_ship_drop_in.sh -- session 55's drop-in rerun with the shipped r1sim-nano
# (since session 55 the same weights as r1sim-grpo: grpo_s54_shr @ 16) on one thread: every mode at seed 0, the
# natives of docs/simulate reused (same demand, same seed), then copied into docs/simulate (report + per-mode JSONs and
# time-space pictures). Seeds 1-2 of the commands and position drives are session 54's runs of the same weights
# (docs/simulate/candidate_s54).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
O=runs/ship55_nano_s0; mkdir -p $O
cp docs/simulate/*_native.json $O/
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw --reuse native > $O.log 2>&1 || exit 1
cp $O/report.md $O/report.json $O/*_commands.json $O/*_commands.time_space.png $O/*_position.json $O/*_position.time_space.png \
   $O/*_position-raw.json $O/*_position-raw.time_space.png $O/*_time_space.png docs/simulate/
touch runs/ship55_drop_in.done
