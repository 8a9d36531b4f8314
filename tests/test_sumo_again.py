"""The "SUMO again" baseline: SUMO rerun from a scenario's saved state with other seeds (r1sim_sumo.evaluate_sumo_again)."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.sumo


@pytest.fixture(scope="module")
def states_data(tmp_path_factory):
    from r1sim_sumo.data.sumo_reference import SumoGenConfig, generate_sumo_scenarios
    from r1sim_sumo.scenario import ScenarioDataset, write_dataset

    root = tmp_path_factory.mktemp("states_again")
    cfg = SumoGenConfig(network="motorway_merge", seed=0, duration_s=12.0, warmup_s=50.0, stride_steps=25, save_states=True)
    write_dataset(root, generate_sumo_scenarios(cfg, state_root=root))
    return ScenarioDataset(root)


def test_sumo_again_differs_from_log_stays_on_road_and_scores_below_log_replay(states_data):
    from r1sim_sumo.evaluate import evaluate_baselines
    from r1sim_sumo.evaluate_sumo_again import again_seeds, sumo_again_sim

    sc = states_data[0]
    assert sc.metadata["seed"] not in again_seeds(sc, 4)
    sim = sumo_again_sim(sc, states_data.root, num_rollouts=3)
    a, ci = sc.agents, sc.current_index
    T = sim.num_steps
    ref_x, ref_y, ref_v = a.x_m[:, ci + 1:ci + 1 + T], a.y_m[:, ci + 1:ci + 1 + T], a.valid[:, ci + 1:ci + 1 + T]
    both = sim.valid & ref_v[None]
    assert both[:, :, 0].sum() >= 0.9 * a.valid[:, ci].sum() * 3  # agents come back after the restore
    err = np.hypot(sim.x_m - ref_x[None], sim.y_m - ref_y[None])[both]
    first = np.hypot(sim.x_m[:, :, 0] - ref_x[None, :, 0], sim.y_m[:, :, 0] - ref_y[None, :, 0])[both[:, :, 0]]
    assert np.median(first) < 0.05  # same start (restored state)
    assert err.max() > 0.02  # ... but another driver-imperfection draw
    assert not np.allclose(sim.x_m[0][sim.valid[0] & sim.valid[1]], sim.x_m[1][sim.valid[0] & sim.valid[1]])
    res = evaluate_baselines(states_data, num_rollouts=3, progress=False, sumo_again=True)
    again, log = res["sumo_again"].summary(), res["log_replay"].summary()
    assert again["realism/rmm"] < log["realism/rmm"]
    assert again["realism/offroad_rate"] <= 0.05  # SUMO keeps its vehicles on the lanes
    assert again["realism/rmm"] > res["constant_velocity"].summary()["realism/rmm"]


def test_redrawn_speed_factors_spread_the_futures(states_data):
    from r1sim_sumo.evaluate_sumo_again import sumo_again_sim

    sc = states_data[0]
    a, ci = sc.agents, sc.current_index

    def mean_err(sim):
        T = sim.num_steps
        both = sim.valid & a.valid[None, :, ci + 1:ci + 1 + T]
        return np.hypot(sim.x_m - a.x_m[None, :, ci + 1:ci + 1 + T], sim.y_m - a.y_m[None, :, ci + 1:ci + 1 + T])[both].mean()

    plain = mean_err(sumo_again_sim(sc, states_data.root, num_rollouts=2))
    redrawn = mean_err(sumo_again_sim(sc, states_data.root, num_rollouts=2, redraw_speed_factor=True))
    assert redrawn > max(0.5, 5 * plain)


def test_evaluate_cli_adds_the_sumo_again_baseline(states_data, tmp_path):
    import json
    import subprocess
    import sys

    out = tmp_path / "eval"
    # in a subprocess, as users run it
    r = subprocess.run([sys.executable, "-m", "r1sim_sumo.cli", "evaluate", "--data", str(states_data.root), "--sampler",
                        "greedy", "--rollouts", "2", "--max-scenarios", "2", "--sumo-again", "redraw", "--threads", "1",
                        "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    rep = json.loads((out / "report.json").read_text())
    assert "SUMO again (speed factors redrawn)" in json.dumps(rep)
    assert "SUMO again" in (out / "report.md").read_text()
