"""A 60 s soak (the full hour is `python scripts/soak.py --sim-seconds 3600`): CSV, plot, balance, no stuck vehicle."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

pytestmark = pytest.mark.sumo


def test_soak_60s(tmp_path):
    from r1sim_sumo.reliability.soak import run_soak

    s = run_soak(60.0, tmp_path, sample_every_s=10.0, stuck_after_s=30.0)
    rows = list(csv.DictReader(open(tmp_path / "soak.csv")))
    assert [float(r["sim_s"]) for r in rows] == [10.0, 20.0, 30.0, 40.0, 50.0, 60.0]
    assert all(float(r["rss_mb"]) > 50 for r in rows)
    assert s.departed > 20 and s.balanced_every_sample and s.matches_sumo_departed, s
    assert s.departed == s.arrived + s.removed + s.running
    assert s.stuck_vehicles == [] and s.policy_errors == 0
    assert (tmp_path / "soak_rss.png").stat().st_size > 5000
    js = json.loads((tmp_path / "soak.json").read_text())
    assert js["passed"] is True and js["memory_judged"] is False and js["max_running"] == 150


def test_continuous_demand_outlasts_bundled_flows(tmp_path):
    import xml.etree.ElementTree as ET

    from r1sim_sumo.reliability.soak import continuous_demand

    cfg = continuous_demand("motorway_merge", 3600.0, tmp_path)
    rou = ET.parse(cfg).getroot().find("./input/route-files").get("value")
    ends = [float(f.get("end")) for f in ET.parse(rou).getroot().iter("flow")]
    assert ends and min(ends) >= 3600.0


def test_rss_leak_separates_population_growth_from_a_leak():
    from r1sim_sumo.reliability.soak import rss_leak

    t = np.arange(0, 3600, 10.0)
    running = np.minimum(20 + t / 5, 400)  # grows then levels off
    grows_with_population = [{"sim_s": s, "running": n, "rss_mb": 300 + 0.25 * n} for s, n in zip(t, running, strict=True)]
    leak, per_vehicle = rss_leak(grows_with_population)
    assert abs(leak) < 1e-6 and abs(per_vehicle - 0.25) < 1e-6
    leaking = [{"sim_s": s, "running": 100, "rss_mb": 300 + 40 * s / 3600} for s in t]  # level population, +40 MB/h
    assert abs(rss_leak(leaking)[0] - 40) < 1e-6
