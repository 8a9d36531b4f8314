#!/usr/bin/env python3
"""Session 64: the two GPU GRPO runs' card-style learning curve against their iteration (0 = the shipped r1sim-nano,
their start), from docs/training/learning_curve_s64/learning_curve.json (5 test scenes per network x 8 rollouts, top-5).

    python docs/training/gpu_s64/plot_curve.py     # writes docs/training/gpu_s64/curve.png
"""
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = Path(__file__).resolve().parent
points = {p["path"]: p for p in json.loads((HERE.parent / "learning_curve_s64" / "learning_curve.json").read_text())["points"]}
START = "runs/grpo_s56_ph_only/ckpt-000024"
RUNS = {  # label -> [(iteration, checkpoint path)]
    "grpo_gpu_s58_ph (control: shr, top-5)": [(0, START), (11, "runs/grpo_gpu_s58_ph/final"),
                                              (24, "runs/grpo_gpu_s58_ph_c64/ckpt-000024"),
                                              (32, "runs/grpo_gpu_s58_ph_c64/final")],
    "grpo_gpu_s58_ph_speedup_k32 (speed-up weight 4, top-32)": [
        (0, START), (10, "runs/grpo_gpu_s58_ph_speedup_k32/ckpt-000010"),
        (24, "runs/grpo_gpu_s58_ph_speedup_k32_c64/ckpt-000024"), (32, "runs/grpo_gpu_s58_ph_speedup_k32_c64/final")],
}
PANELS = (("collision_rate", "collision rate"), ("offroad_rate_log_window", "offroad (log window)"), ("rmm", "RMM"),
          ("free_road_20", "free road 20 m/s -> after 8 s [m/s]"))
fig, axes = plt.subplots(1, len(PANELS), figsize=(4.2 * len(PANELS), 3.4))
for ax, (key, title) in zip(axes, PANELS):
    for label, pts in RUNS.items():
        ax.plot([i for i, _ in pts], [points[p][key] for _, p in pts], "o-", label=label)
    ax.set_title(title)
    ax.set_xlabel("GRPO iteration from r1sim-nano")
axes[0].legend(fontsize=7)
fig.suptitle("Session 64: two GPU GRPO runs continued to iteration 32 (25 test scenes x 8 rollouts, top-5)", fontsize=10)
fig.tight_layout()
fig.savefig(HERE / "curve.png", dpi=110)
print(f"wrote {HERE / 'curve.png'}")
