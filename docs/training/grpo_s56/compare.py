"""Session 56: the GRPO candidates of docs/training/grpo_s56/<label>/ (eval_candidate.sh) beside the shipped r1sim-nano
(its seed-0 rows: docs/simulate/<scenario>_<mode>.json, docs/simulate/filter_holds_s55/room_acceleration_s0.txt,
docs/eval_s54/val_shr_16.json). Prints one markdown table.

    python docs/training/grpo_s56/compare.py mix_12 mix_24 only_12 only_24
"""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
SIM = ROOT / "docs" / "simulate"


def room(lines: list[str], scenario: str) -> str:
    for line in lines:
        if line.startswith(f"{scenario} position"):
            m = re.search(r"median ([-\d.]+), share >= 1.5 m/s\^2 ([\d.]+)", line)
            return f"{m.group(1)} / {m.group(2)}" if m else "?"
    return "n/a"


def run(folder: Path, scenario: str, mode: str) -> dict | None:
    f = folder / f"{scenario}_{mode}.json"
    return json.loads(f.read_text()) if f.exists() else None


def row(label: str, room_lines: list[str], pos: Path, cmd: Path, val: Path) -> str:
    cells = [label]
    for sc in ("motorway_merge", "sumo-game-ramp"):
        cells.append(room(room_lines, sc))
    for sc in ("motorway_merge", "sumo-game-ramp"):
        nat, p, raw = run(SIM, sc, "native"), run(pos, sc, "position"), run(pos, sc, "position-raw")
        cells.append("n/a" if p is None else f"{p['arrived'] / nat['arrived']:.3f} / {p['mean_speed_mps'] / nat['mean_speed_mps']:.2f}"
                     f" / {p['collisions_per_1000_vkm']:.0f}")
        cells.append("n/a" if raw is None else f"{raw['collisions_per_1000_vkm']:.0f}")
    for sc in ("sumo-game-ramp", "sumo-game-grid6"):
        nat, c = run(SIM, sc, "native"), run(cmd, sc, "commands")
        cells.append("n/a" if c is None else f"{c['arrived']} / {nat['arrived']} ({c['arrived'] / nat['arrived']:.3f})")
    if val.exists():
        v = json.loads(val.read_text())
        res = [r for k, r in v["results"].items() if not k.startswith("pretrained")][0]
        cells.append(f"{res['realism/collision_rate']:.4f} ({v['change']['topk:5']['collision_rate_change']:+.1%}) / {res['realism/rmm']:.4f}")
    else:
        cells.append("n/a")
    return "| " + " | ".join(cells) + " |"


def main(labels: list[str]) -> None:
    print("| checkpoint | room accel. median / share >= 1.5 m/s^2: motorway_merge | game/ramp "
          "| position motorway_merge: arrivals / speed vs native / events per 1000 vkm | raw motorway_merge events "
          "| position game/ramp | raw game/ramp | commands game/ramp arrivals | commands game/grid6 "
          "| val collision (vs start) / RMM |")
    print("|" + "---|" * 10)
    print(row("r1sim-nano (shipped)", (SIM / "filter_holds_s55" / "room_acceleration_s0.txt").read_text().splitlines(),
              SIM, SIM, ROOT / "docs" / "eval_s54" / "val_shr_16.json"))
    for label in labels:
        d = HERE / label
        lines = []
        for f in sorted(d.glob("room_*.txt")):
            lines += f.read_text().splitlines()
        print(row(label, lines, d / "position", d / "commands", d / "val.json"))


if __name__ == "__main__":
    main(sys.argv[1:])
