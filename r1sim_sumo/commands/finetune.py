"""``r1sim finetune``: GRPO fine-tuning (R1Sim) or the closed-loop SFT baseline of a pretrained policy."""

from __future__ import annotations

HELP = "fine-tune a pretrained policy by GRPO (R1Sim) or closed-loop SFT (configs/grpo.yaml)"


def add_arguments(p) -> None:
    p.add_argument("--config", default=None, help="YAML config (keys of GRPOConfig); default: built-in defaults")
    p.add_argument("--method", choices=["grpo", "grpo-std", "sft"], default=None,
                   help="grpo: advantage r - mean (paper); grpo-std: also divided by the std; sft: closed-loop SFT (CAT-K)")
    p.add_argument("--set", nargs="*", action="extend", default=[], metavar="KEY=VALUE",
                   help="overrides, e.g. max_iters=100 reward.kind=gated sampler=topk:32 out_dir=runs/x")
    p.add_argument("--resume", action="store_true", help="continue the run in out_dir from its last training state")


def run(args) -> int:
    from r1sim_sumo.train.grpo import run_from_cli

    final = run_from_cli(args.config, args.set, args.resume, args.method)
    print(f"[finetune] checkpoint written to {final}")
    return 0
