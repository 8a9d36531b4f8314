"""Session 56: a candidate's commands drive at seed 0 on the 8 scenarios (runs/s56_LABEL/commands_all, written by
`python examples/full_horizon_runs.py --out runs/s56_LABEL/commands_all --seed 0 --checkpoint CKPT --modes commands`)
beside the shipped r1sim-nano's rows of docs/simulate (same demand and seed, natives from there).

    python docs/training/grpo_s56/compare_commands_seed0.py runs/s56_only_24/commands_all
"""
import json
import sys
from pathlib import Path

SIM = Path(__file__).resolve().parents[2] / "simulate"
SCENARIOS = ["motorway_merge", "lane_drop", "urban_intersection", "roundabout", "urban_grid", "sumo-game-ramp",
             "sumo-game-cross", "sumo-game-grid6"]


def main(folder: str) -> None:
    print("| scenario | native arrivals | nano: arrivals (vs native) / speed vs native / collision events (SUMO or boxes) | candidate: arrivals (vs native) / speed vs native / collision events (SUMO or boxes) |")
    print("|---|---|---|---|")
    for sc in SCENARIOS:
        f = Path(folder) / f"{sc}_commands.json"
        if not f.exists():
            continue
        nat = json.loads((SIM / f"{sc}_native.json").read_text())
        cells = [sc, str(nat["arrived"])]
        for d in (json.loads((SIM / f"{sc}_commands.json").read_text()), json.loads(f.read_text())):
            cells.append(f"{d['arrived']} ({d['arrived'] / nat['arrived']:.3f}) / {d['mean_speed_mps'] / nat['mean_speed_mps']:.3f}"
                         f" / {d['collisions_any']} (native {nat['collisions_any']})")
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(sys.argv[1])
