"""Online PolicyDriver: plans start at the actual pose, have 6 frames, and respect validity."""


import numpy as np
import torch

from r1sim_sumo.scenario import AgentTracks, MapPolylines
from r1sim_sumo.sim.policy_driver import PolicyDriver


def _road():
    xs = np.linspace(0, 300, 61)
    lanes = [np.stack([xs, np.full_like(xs, y)], -1) for y in (0.0, 3.5)]
    edges = [np.stack([xs, np.full_like(xs, y)], -1) for y in (-1.75, 5.25)]
    return MapPolylines.from_lists(lanes + edges, [0, 0, 1, 1], ["l0", "l1", "e0", "e1"], [30, 30, 0, 0], [3.5, 3.5, 0, 0])


def _history(A=5, T=11, speed=10.0):
    h = AgentTracks.empty(A, T)
    t = np.arange(T) * 0.1
    for i in range(A):
        h.x_m[i] = 20 * i + speed * t
        h.y_m[i] = 3.5 * (i % 2)
        h.speed_mps[i] = speed
        h.vx_mps[i] = speed
    h.valid[:] = True
    h.valid[4, -1] = False  # agent 4 left the simulation now
    return h


def test_plan_starts_at_actual_pose_and_has_six_frames(policy):
    drv = PolicyDriver(policy, _road(), sampler="topk:3", seed=0)
    h = _history()
    p = drv.plan(h, tl_state=np.zeros(4, np.int8))
    assert p.xy_m.shape == (5, 6, 2) and p.yaw_rad.shape == (5, 6) and p.speed_mps.shape == (5, 5)
    np.testing.assert_allclose(p.xy_m[:, 0, 0], h.x_m[:, -1], atol=1e-4)
    np.testing.assert_allclose(p.xy_m[:, 0, 1], h.y_m[:, -1], atol=1e-4)
    assert p.ok.tolist() == [True, True, True, True, False]
    assert np.isfinite(p.entropy[:4]).all()
    # the plan moves by what its token says: speeds are consistent with the positions
    np.testing.assert_allclose(p.speed_mps, np.linalg.norm(np.diff(p.xy_m, axis=1), axis=-1) / 0.1, rtol=1e-5)


def test_plan_is_seeded_and_short_history_works(policy):
    a = PolicyDriver(policy, _road(), sampler="topk:20", seed=3).plan(_history())
    b = PolicyDriver(policy, _road(), sampler="topk:20", seed=3).plan(_history())
    np.testing.assert_array_equal(a.token, b.token)
    short = PolicyDriver(policy, _road(), seed=0).plan(_history(T=3))  # a vehicle that just departed
    assert short.ok[:4].all()


def test_cached_map_encoding_matches_a_fresh_full_forward(policy):
    """The driver encodes the network once; logits must equal those of a batch carrying all map tokens."""
    from r1sim_sumo.tokens.batch import TokenizedScene, collate
    from r1sim_sumo.tokens.matching import match_agents

    drv = PolicyDriver(policy, _road(), sampler="greedy", seed=0)
    h = _history()
    tl = np.array([1, 3, 0, 0], np.int8)
    plan = drv.plan(h, tl_state=tl)
    win = AgentTracks.empty(5, 91)
    win.ids, win.agent_type, win.length_m, win.width_m = h.ids, h.agent_type, h.length_m, h.width_m
    for f in (*AgentTracks.PER_STEP, "valid"):
        getattr(win, f)[:, :11] = getattr(h, f)
    mt = drv.map_tokens.select(np.arange(drv.map_tokens.num_tokens))
    mt.tl = np.repeat(tl.astype(np.int64)[mt.polyline][:, None], mt.tl.shape[1], 1)
    batch = collate([TokenizedScene(match_agents(win, policy.vocab), mt, h.ids, np.arange(5), "x")])
    with torch.no_grad():
        logits = policy.model(batch)[0, :, 2]  # teacher-forced logits of token 2 (the next one)
    assert np.array_equal(logits.argmax(-1).numpy()[:4], plan.token[:4])
