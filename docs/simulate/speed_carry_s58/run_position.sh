#!/bin/bash
# usage: bash docs/simulate/speed_carry_s58/run_position.sh CARRY SEED... -- session 58: the shipped r1sim-nano in the
# position drive (safety layer on) with `--speed-carry CARRY` (gains / both / off), the 8 scenarios, one seed after
# another on one thread; native's rows reused from session 57's runs of the same seed (runs/ship57_nano_s0,
# runs/ship57_pos_s1, runs/ship57_pos_s2: same demand; rerun them with `--modes native` where they are missing).
# Outputs runs/carry58_<CARRY>_sS and docs/simulate/speed_carry_s58/<CARRY>_sS/report.{md,json} + pictures.
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
CARRY=$1; shift
for S in "$@"; do
  O=runs/carry58_${CARRY}_s$S; mkdir -p $O
  N=runs/ship57_pos_s$S; [ "$S" = 0 ] && N=runs/ship57_nano_s0
  if ls $N/*_native.json > /dev/null 2>&1; then cp $N/*_native.* $O/; REUSE="--reuse native"; else REUSE=""; fi
  python examples/full_horizon_runs.py --out $O --seed $S --modes native position $REUSE --speed-carry $CARRY > $O.log 2>&1 \
    || { tail $O.log; exit 1; }
  D=docs/simulate/speed_carry_s58/${CARRY}_s$S; mkdir -p $D && cp $O/report.md $O/report.json $O/*_time_space.png $D/
done
