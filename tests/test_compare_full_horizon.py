"""scripts/compare_full_horizon.py: each run is compared with the native row of its own report, and a label given
twice gets the mean of its reports."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


def _report(path: Path, native: int, policy: int, speed: float, events: int = 0, vkm: float = 100.0) -> Path:
    rows = [{"scenario": "merge", "mode": "native", "arrived": native, "mean_speed_mps": 20.0},
            {"scenario": "merge", "mode": "commands", "arrived": policy, "mean_speed_mps": speed,
             "collisions_either": events, "vkm": vkm, "collisions_per_1000_vkm": 1000.0 * events / vkm},
            {"scenario": "ramp", "mode": "commands", "arrived": 5, "mean_speed_mps": 1.0}]  # no native row: skipped
    path.write_text(json.dumps(rows))
    return path


def test_ratios_use_each_reports_own_native_and_labels_are_averaged(tmp_path, capsys, repo_script):
    mod = repo_script("scripts/compare_full_horizon.py")
    a = _report(tmp_path / "a.json", 100, 90, 10.0)
    b = _report(tmp_path / "b.json", 50, 50, 20.0)
    assert mod.ratios(a, "commands")["merge"][:2] == (0.9, 0.5)
    assert mod.main([f"x={a}", f"x={b}"]) == 0
    out = capsys.readouterr().out
    assert "| merge | 0.900 (0.50) | 1.000 (1.00) | 0.950 (0.75) |" in out
    assert "ramp" not in out
    c = _report(tmp_path / "c.json", 100, 80, 10.0, events=3, vkm=150.0)
    assert mod.main([f"x={c}", "--events"]) == 0
    out = capsys.readouterr().out
    assert "| merge | 0.800 (0.50, 20) |" in out  # 3 events in 150 vehicle-km
    assert "| **sum: arrivals (native's) / events (per 1000 vkm)** | 80 (100) / 3 (20) |" in out
    with pytest.raises(SystemExit):
        mod.main([str(a)])  # no LABEL=
