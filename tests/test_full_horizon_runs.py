"""examples/full_horizon_runs.py: each mode becomes the ``r1sim simulate`` command it names, and ``--safety`` reaches
the commands and position drives but never position-raw (which is the drive without the safety layer)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest


def _flag(cmd: list[str], name: str) -> str | None:
    return cmd[cmd.index(name) + 1] if name in cmd else None


@pytest.mark.parametrize("safety", ["krauss", "none"])
def test_modes_become_simulate_commands_with_the_asked_safety_layer(tmp_path, monkeypatch, safety, repo_script):
    mod = repo_script("examples/full_horizon_runs.py")
    seen: dict[str, list[str]] = {}

    def fake_run(cmd, capture_output, text):  # writes the summary r1sim simulate would write
        js = Path(_flag(cmd, "--json"))
        js.write_text(json.dumps({"arrived": 1}))
        seen[js.stem.split("_", 1)[1]] = cmd
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(mod.subprocess, "run", fake_run)
    for mode in mod.MODES:
        s = mod.run_one("net", tmp_path / "net.sumocfg", mode, 60.0, tmp_path, None, 3, safety=safety)
        assert s["mode"] == mode
    assert "--native" in seen["native"] and "--drive" not in seen["native"]
    assert _flag(seen["commands"], "--drive") == "commands" and _flag(seen["commands"], "--safety") == safety
    assert _flag(seen["position"], "--drive") == "position" and _flag(seen["position"], "--safety") == safety
    assert _flag(seen["position-raw"], "--drive") == "position" and _flag(seen["position-raw"], "--safety") == "none"
    assert _flag(seen["position-raw"], "--standstill-handoff") == "0"
    assert _flag(seen["commands"], "--standstill-handoff") == "5"
    assert all(_flag(c, "--seed") == "3" and _flag(c, "--end") == "60" for c in seen.values())
    # no --sampler: `r1sim simulate` picks each drive's own default (SumoController's DROP_IN_SAMPLERS)
    assert all("--sampler" not in c for c in seen.values())
    # no --speed-carry either: each drive's own (DROP_IN_SPEED_CARRY); an asked one reaches the policy modes only
    assert all("--speed-carry" not in c for c in seen.values())
    for mode in mod.MODES:
        mod.run_one("net", tmp_path / "net.sumocfg", mode, 60.0, tmp_path, None, 3, safety=safety, speed_carry="off")
    assert "--speed-carry" not in seen["native"]
    assert all(_flag(seen[m], "--speed-carry") == "off" for m in ("commands", "position", "position-raw"))
