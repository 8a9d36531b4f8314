#!/bin/bash
# usage: bash docs/simulate/quantile_s53/run_report.sh -- docs/simulate/report.{md,json} with the commands drive's new default
# sampler (quantile:0.7,0.1), seed 0: the commands rows rerun, the native, position and position-raw rows of session 52
# (same shipped r1sim-nano; the position drive keeps median:0.1) reused from docs/simulate. Then copies the new rows back.
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
O=runs/ship53_s0; rm -rf $O; mkdir -p $O
cp docs/simulate/*_native.* docs/simulate/*_position.* docs/simulate/*_position-raw.* $O/
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw --reuse native position position-raw > $O.log 2>&1
cp $O/report.md $O/report.json $O/*_commands.* docs/simulate/
for f in $O/*_time_space.png; do cp "$f" docs/simulate/; done
