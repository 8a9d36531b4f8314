#!/bin/bash
# usage: bash docs/simulate/candidate_s52/run_ship_drop_in.sh -- session 52's drop-in reruns with the shipped r1sim-nano on
# one thread: every mode at seed 0 (native and commands reused: the natives of docs/simulate, the commands rows of
# runs/d51_ntop5_30_s0, the same weights run by docs/simulate/candidate_s51/run_commands.sh), then the position drive
# at seeds 1 and 2 (natives of runs/med47_cmd_sS).
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
for d in runs/d51_ntop5_30_s0 runs/med47_cmd_s1 runs/med47_cmd_s2; do
  [ -d $d ] || { echo "$0: $d is missing: it holds the reused rows (runs/d51_ntop5_30_s0: bash docs/simulate/candidate_s51/run_commands.sh ntop5_30 r1sim_sumo/checkpoints/r1sim-nano 0; runs/med47_cmd_sS: python examples/full_horizon_runs.py --out runs/med47_cmd_sS --seed S --modes native)" >&2; exit 1; }
done
O=runs/ship52_s0; mkdir -p $O
cp docs/simulate/*_native.json $O/ && cp runs/d51_ntop5_30_s0/*_commands.* $O/
python examples/full_horizon_runs.py --out $O --seed 0 --modes native commands position position-raw --reuse native commands > $O.log 2>&1
for S in 1 2; do
  O=runs/ship52_pos_s$S; mkdir -p $O; cp runs/med47_cmd_s$S/*_native.json $O/
  python examples/full_horizon_runs.py --out $O --seed $S --modes native position --reuse native > $O.log 2>&1
done
touch runs/ship52_drop_in.done
