"""Evaluation pipeline on synthetic curved-road scenes with an untrained policy (structure, not quality)."""

import json

import numpy as np
import pytest

from r1sim_sumo.evaluate import constant_velocity_sim, evaluate_baselines, evaluate_policy, write_report
from r1sim_sumo.scenario import AgentTracks, MapPolylines, Scenario


def curved_scene(seed: int, n_agents: int = 4) -> Scenario:
    """Agents driving along a 60 m-radius arc at 8-12 m/s; lane centre + road edges of the arc."""
    rng = np.random.default_rng(seed)
    R = 60.0
    th = np.linspace(-0.2, 2.5, 200)
    arc = lambda r: np.stack([r * np.cos(th), r * np.sin(th)], -1)  # noqa: E731
    mp = MapPolylines.from_lists([arc(R), arc(R - 2), arc(R + 2)], [0, 1, 1], ["lane", "in", "out"], [15, 0, 0], [4, 0, 0])
    a = AgentTracks.empty(n_agents, 91)
    t = np.arange(91) * 0.1
    for i in range(n_agents):
        v = rng.uniform(8, 12)
        phi = 0.1 * i * 1.5 + v / R * t
        a.x_m[i], a.y_m[i] = R * np.cos(phi), R * np.sin(phi)
        a.yaw_rad[i] = (phi + np.pi / 2 + np.pi) % (2 * np.pi) - np.pi
        a.speed_mps[i] = v
        a.vx_mps[i], a.vy_mps[i] = -v * np.sin(phi), v * np.cos(phi)
        a.ids[i] = f"v{i}"
    a.valid[:] = True
    return Scenario(a, mp, {"source": "test", "network": "arc", "seed": seed}).validate()


def test_constant_velocity_leaves_the_arc_and_scores_below_log_replay():
    scs = [curved_scene(s) for s in range(2)]
    base = evaluate_baselines(scs, num_rollouts=4, progress=False)
    lr, cv = base["log_replay"].summary(), base["constant_velocity"].summary()
    assert lr["realism/rmm"] > cv["realism/rmm"]
    assert lr["realism/offroad_rate"] == 0.0 and cv["realism/offroad_rate"] > 0.5
    sim = constant_velocity_sim(scs[0])
    assert sim.x_m.shape == (1, 4, 80)


def test_policy_evaluation_and_report(policy, tmp_path):
    scs = [curved_scene(s) for s in range(3)]
    res = evaluate_policy(policy, scs, "entropy:16,80", num_rollouts=3, seed=0, batch_scenes=2, progress=False)
    assert len(res.rows) == 3 and all(np.isfinite(r["realism/rmm"]) for r in res.rows)
    assert 0.0 <= res.summary()["realism/collision_rate"] <= 1.0
    assert len(res.k_by_step) == 2 and len(res.k_by_step[0]) == 16
    base = evaluate_baselines(scs, num_rollouts=3, progress=False)
    out = write_report(tmp_path, {"entropy:16,80": res, **{v.name: v for v in base.values()}}, {"data": "synthetic", "rollouts": 3})
    rep = json.loads((out / "report.json").read_text())
    assert set(rep["summary"]) == {"entropy:16,80", "log replay", "constant velocity"}
    assert "summary_easy" in rep and "summary_hard" in rep
    md = (out / "report.md").read_text()
    assert "| log replay |" in md and (out / "entropy_and_k.png").stat().st_size > 1000


def test_multi_seed_report_has_std(policy, tmp_path):
    scs = [curved_scene(s) for s in range(2)]
    runs = [evaluate_policy(policy, scs, "topk:5", num_rollouts=2, seed=s, batch_scenes=2, progress=False) for s in (0, 1)]
    out = write_report(tmp_path, {"topk:5": runs}, {"data": "synthetic", "rollouts": 2})
    rep = json.loads((out / "report.json").read_text())
    assert rep["summary"]["topk:5"]["num_seeds"] == 2 and "realism/rmm/std" in rep["summary"]["topk:5"]
    assert "±" in (out / "report.md").read_text()


def test_matched_reference_follows_the_log_and_stays_on_the_arc():
    """The vocabulary's floor: the logged future rebuilt from its matched tokens (shipped vocabulary)."""
    import r1sim_sumo
    from r1sim_sumo.evaluate import matched_reference_sim
    from r1sim_sumo.metrics import compute_realism

    vocab = r1sim_sumo.load_policy().vocab
    sc = curved_scene(0)
    sim = matched_reference_sim(sc, vocab)
    assert sim.x_m.shape == (1, 4, 80) and sim.valid.all()
    ci = sc.current_index
    err = np.hypot(sim.x_m[0] - sc.agents.x_m[:, ci + 1:], sim.y_m[0] - sc.agents.y_m[:, ci + 1:])
    assert err.mean() < 0.3 and err.max() < 1.0, (err.mean(), err.max())
    d = compute_realism(sc, sim).to_dict()
    assert d["realism/offroad_rate"] == 0.0
    cv = compute_realism(sc, constant_velocity_sim(sc)).to_dict()
    assert cv["realism/offroad_rate"] > 0.5  # the same scene is hard: only following the arc keeps it on the road


def test_sumo_scenes_by_network_takes_a_spread_sample():
    from r1sim_sumo.evaluate import sumo_scenes_by_network

    scs = [curved_scene(s) for s in range(10)]
    for i, sc in enumerate(scs):
        sc.metadata.update(source="sumo" if i != 7 else "highway-env", network=f"n{i % 2}")
    out = sumo_scenes_by_network(scs, per_network=2, every=3)  # scenes 0, 3, 6, 9 (7 is not SUMO anyway)
    assert {k: [s.metadata["seed"] for s in v] for k, v in out.items()} == {"n0": [0, 6], "n1": [3, 9]}


def test_evaluation_without_the_desired_speed_changes_only_models_that_use_it():
    """``desired_speed="unknown"`` hides the log's hindsight speed: same rollouts for a model whose desired-speed
    embedding is still zero, other rollouts once it is trained (here: set at random)."""
    import torch

    from r1sim_sumo.model.untrained import untrained_policy

    pol = untrained_policy(0, desired_speed_input=True)
    scs = [curved_scene(s) for s in range(2)]

    def rmm(desired):
        res = evaluate_policy(pol, scs, "topk:5", num_rollouts=2, seed=0, batch_scenes=2, progress=False, desired_speed=desired)
        return [r["realism/rmm"] for r in res.rows]

    assert rmm("log") == rmm("unknown")
    torch.nn.init.normal_(pol.model.desired_speed_emb.lin2.weight, std=1.0)
    assert rmm("log") != rmm("unknown")
    with pytest.raises(ValueError, match="desired_speed"):
        evaluate_policy(pol, scs, desired_speed="future", progress=False)


def test_decoding_changes_only_the_kinematic_states_and_a_bad_name_fails_early(policy):
    scs = [curved_scene(s) for s in range(2)]
    res = {d: evaluate_policy(policy, scs, "topk:5", num_rollouts=2, seed=0, batch_scenes=2, progress=False, decoding=d)
           for d in ("central", "tokens")}
    a, b = res["central"].rows, res["tokens"].rows
    assert [r["realism/num_evaluated_agents"] for r in a] == [r["realism/num_evaluated_agents"] for r in b]
    assert any(r1["likelihood/linear_acceleration"] != r2["likelihood/linear_acceleration"] for r1, r2 in zip(a, b, strict=True))
    with pytest.raises(ValueError, match="decoding"):
        evaluate_policy(policy, scs, "topk:5", num_rollouts=2, progress=False, decoding="spline")
