"""``r1sim pretrain``: next-token pretraining of the traffic policy."""

from __future__ import annotations

HELP = "pretrain the tokenized traffic policy by next-token prediction (configs/pretrain.yaml)"


def add_arguments(p) -> None:
    p.add_argument("--config", default=None, help="YAML config (keys of PretrainConfig); default: built-in defaults")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="overrides, e.g. max_steps=100 out_dir=runs/x")
    p.add_argument("--resume", action="store_true", help="continue the run in out_dir from its last checkpoint")


def run(args) -> int:
    from r1sim_sumo.train.pretrain import run_from_cli

    final = run_from_cli(args.config, args.set, args.resume)
    print(f"[pretrain] checkpoint written to {final}")
    return 0
