#!/bin/bash
# usage: bash docs/eval_s54/sampler_table_grpo.sh -- session 54: the sampler table's command for r1sim-grpo, split in two
# one-thread halves run side by side (the nano's table: docs/eval_nano_test, the same command with one --sampler list)
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
export OMP_NUM_THREADS=1
E="r1sim evaluate --checkpoint r1sim-grpo --data data/generated/default/test --rollouts 32 --seeds 0 1 2 3 4 --max-scenarios 8 --threads 1"
$E --sampler topk:5 topk:32 --out docs/eval_s54/sampler_grpo54_a > runs/sampler54_a.log 2>&1 &
$E --sampler topk:64 entropy:16,80 --out docs/eval_s54/sampler_grpo54_b > runs/sampler54_b.log 2>&1
wait
