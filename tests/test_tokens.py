"""Tokenizer tests: motion vocabulary, rolling matching, state reconstruction, map tokens, batches, CLI.

All data is synthetic: kinematic-bicycle tracks and hand-made polylines.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from r1sim_sumo.geometry import box_corners, wrap_angle
from r1sim_sumo.scenario import (
    CYCLIST,
    PEDESTRIAN,
    VEHICLE,
    AgentTracks,
    MapPolylines,
    Scenario,
    ScenarioDataset,
    write_dataset,
)
from r1sim_sumo.tokens import (
    CURRENT_POSE,
    N_POSE,
    N_TOK,
    STEPS_PER_TOKEN,
    MotionVocab,
    TokenizedDataset,
    VocabBuildConfig,
    build_vocab,
    build_vocab_from_dataset,
    collate,
    extract_segments,
    kdisk_cluster,
    match_agents,
    reconstruct_states,
    tokenize_map,
    tokenize_scenario,
)
from r1sim_sumo.tokens.matching import speed_band
from r1sim_sumo.tokens.motion_vocab import segment_corners, synthetic_segments

torch.set_num_threads(1)
T91 = 91


# ---------------------------------------------------------------------------- synthetic data


def bicycle_tracks(n_agents: int, n_steps: int = T91, seed: int = 0, types=(VEHICLE,)) -> AgentTracks:
    """Kinematic-bicycle tracks (wheelbase 2.8 m) integrated at 100 Hz, sampled at 10 Hz.

    Random start pose, speed 0-20 m/s, smooth acceleration and steering profiles; some agents brake to a stop.
    """
    rng = np.random.default_rng(seed)
    tr = AgentTracks.empty(n_agents, n_steps)
    sub = 10
    dt = 0.1 / sub
    n_fine = (n_steps - 1) * sub + 1
    t = np.arange(n_fine) * dt
    for i in range(n_agents):
        x, y = rng.uniform(-100, 100, 2)
        yaw = rng.uniform(-np.pi, np.pi)
        v = rng.uniform(0.0, 20.0)
        a_amp, a_w, a_ph = rng.uniform(0, 2.0), rng.uniform(0.1, 0.8), rng.uniform(0, 6.3)
        d_amp, d_w, d_ph = rng.uniform(0, 0.15), rng.uniform(0.1, 0.6), rng.uniform(0, 6.3)
        brake = rng.random() < 0.2
        xs, ys, yaws, vs = np.empty(n_fine), np.empty(n_fine), np.empty(n_fine), np.empty(n_fine)
        for j in range(n_fine):
            xs[j], ys[j], yaws[j], vs[j] = x, y, yaw, v
            acc = -3.0 if brake else a_amp * np.sin(a_w * t[j] + a_ph)
            steer = d_amp * np.sin(d_w * t[j] + d_ph)
            x += v * np.cos(yaw) * dt
            y += v * np.sin(yaw) * dt
            yaw += v / 2.8 * np.tan(steer) * dt
            v = max(v + acc * dt, 0.0)
        k = slice(None, None, sub)
        tr.x_m[i], tr.y_m[i], tr.yaw_rad[i], tr.speed_mps[i] = xs[k], ys[k], wrap_angle(yaws[k]), vs[k]
        tr.vx_mps[i], tr.vy_mps[i] = vs[k] * np.cos(yaws[k]), vs[k] * np.sin(yaws[k])
    tr.valid[:] = True
    tr.agent_type = np.asarray([types[i % len(types)] for i in range(n_agents)], np.int8)
    tr.ids = np.array([f"veh{i}" for i in range(n_agents)])
    return tr.astype_canonical()


def straight_map(n_lanes: int = 2, length_m: float = 120.0, tl: bool = True) -> MapPolylines:
    """Parallel straight lanes along +x plus two road edges; lane 0 has a signal cycling with time."""
    lines, kinds, ids = [], [], []
    for j in range(n_lanes):
        lines.append(np.stack([np.linspace(-length_m / 2, length_m / 2, 13), np.full(13, 3.5 * j)], 1))
        kinds.append(0)
        ids.append(f"e_{j}")
    for j, yy in enumerate((-1.75, 3.5 * n_lanes - 1.75)):
        lines.append(np.array([[-length_m / 2, yy], [length_m / 2, yy]]))
        kinds.append(1)
        ids.append(f"e#{j}")
    L = len(lines)
    tls = None
    if tl:
        tls = np.zeros((L, T91), np.int8)
        tls[0] = 1 + (np.arange(T91) // 30) % 3
    return MapPolylines.from_lists(lines, kinds, ids, [13.9 if k == 0 else 0 for k in kinds], [3.5 if k == 0 else 0 for k in kinds], tls)


@pytest.fixture(scope="module")
def vocab() -> MotionVocab:
    segs = {VEHICLE: np.concatenate([extract_segments(bicycle_tracks(40, seed=s)) for s in range(3)])}
    cfg = VocabBuildConfig(size=(1024, 64, 64), tolerance_m=(0.04, 0.1, 0.1), min_real_segments=1000, n_synthetic=20_000)
    return build_vocab(segs, cfg)


# ---------------------------------------------------------------------------- vocabulary


def test_segments_are_in_start_frame_and_invariant_to_world_pose():
    tr = bicycle_tracks(3, n_steps=30, seed=1)
    seg = extract_segments(tr)
    assert seg.shape == (3 * (30 - 5), 6, 3)
    assert np.allclose(seg[:, 0], 0.0, atol=1e-6)
    moved = tr.select(np.arange(3))
    c, s = np.cos(1.0), np.sin(1.0)
    moved.x_m, moved.y_m = c * tr.x_m - s * tr.y_m + 500.0, s * tr.x_m + c * tr.y_m - 200.0
    moved.yaw_rad = wrap_angle(tr.yaw_rad + 1.0)
    assert np.allclose(extract_segments(moved), seg, atol=2e-3)
    tr.valid[0, 10] = False  # windows touching an invalid step disappear (6 of agent 0's 25)
    assert len(extract_segments(tr)) == len(seg) - 6


def test_vocab_token0_standing_still_and_sizes(vocab):
    for t in (VEHICLE, CYCLIST, PEDESTRIAN):
        assert np.all(vocab.traj[t][0] == 0.0)
        rest = segment_corners(np.zeros((1, 6, 3)), t)[0]
        assert np.allclose(vocab.corners[t][0], rest)
        assert vocab.traj[t].shape[1:] == (6, 3) and vocab.corners[t].shape[1:] == (6, 4, 2)
    assert vocab.sizes[0] <= 1024 and vocab.sizes[1] <= 64 and vocab.sizes[2] <= 64
    assert vocab.meta["source"] == {"vehicle": "data", "cyclist": "synthetic", "pedestrian": "synthetic"}


def test_vocab_no_duplicates(vocab):
    for t in (VEHICLE, CYCLIST, PEDESTRIAN):
        c = torch.from_numpy(vocab.corners[t]).reshape(len(vocab.corners[t]), -1, 2)
        d = (c[:, None] - c[None]).norm(dim=-1).mean(-1)  # [V, V] mean corner distance
        d.fill_diagonal_(float("inf"))
        assert float(d.min()) > vocab.meta["tolerance_m"][["vehicle", "cyclist", "pedestrian"][t]]


def test_kdisk_cap_and_cover():
    seg = synthetic_segments(VEHICLE, 5000, seed=3)
    cand = np.concatenate([np.zeros((1, 6, 3), np.float32), seg])
    corners = segment_corners(cand, VEHICLE)
    picked, cov = kdisk_cluster(corners, 0.01, 50, force_first=True)
    assert len(picked) == 50 and picked[0] == 0 and cov < 1.0
    picked, cov = kdisk_cluster(corners, 2.0, 10_000)
    assert cov == 1.0 and len(picked) < 200
    # every candidate lies within the tolerance of some centre when the cover is complete
    c = torch.from_numpy(corners).reshape(len(corners), -1, 2)
    d = (c[:, None] - c[picked][None]).norm(dim=-1).mean(-1).min(1).values
    assert float(d.max()) <= 2.0 + 1e-6


def test_vocab_save_load_identity_and_fingerprint(vocab, tmp_path):
    p = vocab.save(tmp_path / "v.safetensors")
    v2 = MotionVocab.load(p)
    assert v2.fingerprint() == vocab.fingerprint()
    for t in (VEHICLE, CYCLIST, PEDESTRIAN):
        assert np.array_equal(v2.traj[t], vocab.traj[t]) and np.array_equal(v2.corners[t], vocab.corners[t])
    assert json.loads((tmp_path / "v.safetensors.json").read_text())["fingerprint"] == vocab.fingerprint()
    v3 = MotionVocab.from_dict(vocab.to_dict())
    assert v3.fingerprint() == vocab.fingerprint() and v3.meta["source"] == vocab.meta["source"]
    traj = {t: vocab.traj[t].copy() for t in (VEHICLE, CYCLIST, PEDESTRIAN)}
    traj[VEHICLE][5, 3, 0] += 1e-3
    assert MotionVocab.from_traj(traj).fingerprint() != vocab.fingerprint()
    d = vocab.to_dict()
    d["vocab/traj/vehicle"] = d["vocab/traj/vehicle"] + 0.1  # tampered tensors are refused
    with pytest.raises(ValueError, match="fingerprint"):
        MotionVocab.from_dict(d)


# ---------------------------------------------------------------------------- matching


def _constant_curvature(speed_mps=12.0, yaw_rate=0.15, n_steps=T91) -> AgentTracks:
    tr = AgentTracks.empty(1, n_steps)
    t = np.arange(n_steps) * 0.1
    r = speed_mps / yaw_rate
    tr.x_m[0], tr.y_m[0] = 30.0 + r * np.sin(yaw_rate * t), -20.0 + r * (1 - np.cos(yaw_rate * t))
    tr.yaw_rad[0] = wrap_angle(yaw_rate * t)
    tr.speed_mps[0] = speed_mps
    tr.valid[:] = True
    tr.length_m[:], tr.width_m[:] = 4.8, 2.0
    return tr


def _pose_err(tk, tr):
    b = np.arange(tk.pose_xy.shape[1]) * STEPS_PER_TOKEN
    return np.hypot(tk.pose_xy[..., 0] - tr.x_m[:, b], tk.pose_xy[..., 1] - tr.y_m[:, b])  # [A, P]


def test_rolling_matching_does_not_drift(vocab):
    tr = _constant_curvature()
    tk = match_agents(tr, vocab)
    assert tk.token.shape == (1, N_TOK) and tk.pose_xy.shape == (1, N_POSE, 2) and tk.token_valid.all()
    err = _pose_err(tk, tr)[0]
    # naive: match each step independently from the ground-truth pose, then chain the tokens open-loop
    naive_tok = np.zeros(N_TOK, np.int64)
    for k in range(N_TOK):
        one = tr.slice_steps(5 * k, 5 * k + 6)
        naive_tok[k] = match_agents(one, vocab).token[0, 0]
    xy, _ = reconstruct_states(torch.tensor([tr.x_m[0, 0], tr.y_m[0, 0]], dtype=torch.float64),
                               torch.tensor(tr.yaw_rad[0, 0], dtype=torch.float64), torch.from_numpy(naive_tok), vocab,
                               torch.tensor(VEHICLE))
    naive_err = np.hypot(xy[::5, 0].numpy() - tr.x_m[0, ::5], xy[::5, 1].numpy() - tr.y_m[0, ::5])
    assert err.max() < 0.3, err
    assert err[-1] < naive_err[-1]


def test_noised_matching_draws_near_tokens_and_recovers(vocab):
    """Noised rolling matching (training): tokens from the 5 nearest, chain pulled back to the track, seeded."""
    tr = bicycle_tracks(12, seed=5)
    exact = match_agents(tr, vocab)
    assert np.array_equal(match_agents(tr, vocab, noise_top_k=1).token, exact.token)
    a = match_agents(tr, vocab, noise_top_k=5, rng=np.random.default_rng(1))
    b = match_agents(tr, vocab, noise_top_k=5, rng=np.random.default_rng(1))
    c = match_agents(tr, vocab, noise_top_k=5, rng=np.random.default_rng(2))
    assert np.array_equal(a.token, b.token) and not np.array_equal(a.token, c.token)
    ok = exact.token_valid
    assert 0.3 < (a.token != exact.token)[ok].mean() < 0.95  # most tokens change, yet ...
    err_a, err_x = _pose_err(a, tr), _pose_err(exact, tr)
    # ... the chain does not drift away (an open-loop chain of wrong tokens would be metres off after 9 s)
    assert err_a[:, -1].mean() < err_x[:, -1].mean() + 0.75 and err_a.max() < err_x.max() + 3.0, (err_a.max(), err_x.max())
    # every drawn token is among the 5 nearest to the logged end pose seen from its own (noised) start pose
    from r1sim_sumo.tokens import BOX_SIZE_M

    end = vocab.corners[VEHICLE][:, -1].reshape(vocab.size(VEHICLE), -1)  # [V, 8]
    for i, k in zip(*np.nonzero(ok), strict=True):
        c0, s0 = np.cos(a.pose_yaw[i, k]), np.sin(a.pose_yaw[i, k])
        dx, dy = tr.x_m[i, 5 * k + 5] - a.pose_xy[i, k, 0], tr.y_m[i, 5 * k + 5] - a.pose_xy[i, k, 1]
        g = box_corners(c0 * dx + s0 * dy, -s0 * dx + c0 * dy, wrap_angle(tr.yaw_rad[i, 5 * k + 5] - a.pose_yaw[i, k]),
                        *BOX_SIZE_M[VEHICLE]).reshape(-1)
        d = np.linalg.norm((end - g).reshape(-1, 4, 2), axis=-1).mean(-1)
        assert d[a.token[i, k]] <= np.sort(d)[4] + 1e-3
        assert d[a.target[i, k]] <= d.min() + 1e-3  # the label: the nearest, recovering token
    assert exact.target is None and a.select([0, 2]).target.shape == (2, N_TOK)
    with pytest.raises(ValueError, match="rng"):
        match_agents(tr, vocab, noise_top_k=5)


def test_noise_that_keeps_the_speed_draws_only_tokens_of_the_nearest_ones_speed(vocab):
    """``noise_speed_tol_mps``: each drawn token's mean speed is within the tolerance of its label's (the nearest
    token from the same noised start pose); a wide tolerance is the free noise, draw for draw."""
    tr = bicycle_tracks(12, seed=5)
    end = vocab.traj[VEHICLE][:, -1]
    speed = np.hypot(end[:, 0], end[:, 1]) / 0.5  # [V] mean speed [m/s]
    free = match_agents(tr, vocab, noise_top_k=5, rng=np.random.default_rng(1))
    for tol in (0.0, 0.3):
        kept = match_agents(tr, vocab, noise_top_k=5, rng=np.random.default_rng(1), noise_speed_tol_mps=tol)
        ok = kept.token_valid
        assert (np.abs(speed[kept.token] - speed[kept.target])[ok] <= tol + 1e-9).all()
        moved = (np.abs(speed[free.token] - speed[free.target])[free.token_valid] > 0.3).mean()
        assert moved > 0.1  # the free noise does change the speed of many tokens
    wide = match_agents(tr, vocab, noise_top_k=5, rng=np.random.default_rng(1), noise_speed_tol_mps=1e9)
    assert (wide.token_valid == free.token_valid).all()
    # the same candidates, drawn by another formula of the same generator: as noisy as the free draw
    ok = free.token_valid
    assert abs((wide.token != wide.target)[ok].mean() - (free.token != free.target)[ok].mean()) < 0.15


def test_an_asymmetric_speed_band_draws_only_slower_tokens(vocab):
    """``noise_speed_tol_mps=(below, above)``: drawn tokens are at most ``below`` slower and ``above`` faster than the
    nearest; ``(1.0, 0.0)`` never draws a faster one but does draw slower ones; a bad band is refused."""
    tr = bicycle_tracks(12, seed=5)
    end = vocab.traj[VEHICLE][:, -1]
    speed = np.hypot(end[:, 0], end[:, 1]) / 0.5  # [V] mean speed [m/s]
    slow = match_agents(tr, vocab, noise_top_k=5, rng=np.random.default_rng(1), noise_speed_tol_mps=(1.0, 0.0))
    dv = (speed[slow.token] - speed[slow.target])[slow.token_valid]
    assert (dv <= 1e-9).all() and (dv >= -1.0 - 1e-9).all()
    assert (dv < -0.05).mean() > 0.1  # slower draws do happen
    same = match_agents(tr, vocab, noise_top_k=5, rng=np.random.default_rng(1), noise_speed_tol_mps=(0.3, 0.3))
    sym = match_agents(tr, vocab, noise_top_k=5, rng=np.random.default_rng(1), noise_speed_tol_mps=0.3)
    assert (same.token == sym.token).all()  # a number is the symmetric band
    assert speed_band([0.5, 0]) == (0.5, 0.0) and speed_band(0.2) == (0.2, 0.2)
    for bad in ((-0.1, 0.0), (0.1,), "x"):
        with pytest.raises(ValueError):
            speed_band(bad)


def test_matching_recovers_vocab_generated_tokens(vocab):
    rng = np.random.default_rng(7)
    A = 6
    tokens = rng.integers(0, vocab.size(VEHICLE), (A, N_TOK))
    xy0 = torch.from_numpy(rng.uniform(-50, 50, (A, 2)))
    yaw0 = torch.from_numpy(rng.uniform(-3, 3, A))
    xy, yaw = reconstruct_states(xy0, yaw0, torch.from_numpy(tokens), vocab, torch.zeros(A, dtype=torch.long))
    assert xy.shape == (A, T91, 2) and yaw.shape == (A, T91)
    tr = AgentTracks.empty(A, T91)
    tr.x_m, tr.y_m, tr.yaw_rad = xy[..., 0].numpy(), xy[..., 1].numpy(), yaw.numpy()
    tr.valid[:] = True
    tk = match_agents(tr, vocab)
    # a token is identified by its end pose only: tokens with (near) identical end frames are ambiguous
    end = vocab.corners[VEHICLE][:, -1].reshape(len(vocab.corners[VEHICLE]), -1)
    ambiguous = np.linalg.norm(end[tokens][..., None, :] - end[None, None], axis=-1)  # [A, K, V]
    ambiguous = (np.sort(ambiguous, -1)[..., 1] < 1e-4)
    assert np.array_equal(tk.token[~ambiguous], tokens[~ambiguous])
    assert (~ambiguous).mean() > 0.95


def test_reconstruct_states_reproduces_matched_boundaries(vocab):
    tr = bicycle_tracks(8, seed=11, types=(VEHICLE, CYCLIST, PEDESTRIAN))
    tk = match_agents(tr, vocab)
    xy, yaw = reconstruct_states(torch.from_numpy(tk.pose_xy[:, 0]).double(), torch.from_numpy(tk.pose_yaw[:, 0]).double(),
                                 torch.from_numpy(tk.token), vocab, torch.from_numpy(tk.agent_type))
    assert np.allclose(xy[:, ::5].numpy(), tk.pose_xy, atol=1e-3)
    assert np.allclose(wrap_angle(yaw[:, ::5].numpy() - tk.pose_yaw), 0.0, atol=1e-4)
    # 10 Hz states stay close to the ground truth (rolling matching bounds the error)
    assert np.hypot(xy[..., 0].numpy() - tr.x_m, xy[..., 1].numpy() - tr.y_m)[tr.agent_type == VEHICLE].max() < 0.5


def test_matching_validity_and_reappearing_agents(vocab):
    tr = bicycle_tracks(3, seed=5)
    tr.valid[0, :23] = False  # first valid boundary is state 25 (pose 5)
    tr.valid[1, 40:50] = False  # invalid at boundary 45 (pose 9): tokens 8, 9 invalid; re-enters at pose 10
    tk = match_agents(tr, vocab)
    assert not tk.pose_valid[0, :5].any() and tk.pose_valid[0, 5:].all()
    assert (tk.token[0, :5] == -1).all() and (tk.token[0, 5:] >= 0).all()
    assert np.allclose(tk.pose_xy[0, 5], [tr.x_m[0, 25], tr.y_m[0, 25]])  # starts at the ground truth
    assert not tk.token_valid[1, 8] and not tk.token_valid[1, 9] and tk.token_valid[1, 10]
    assert np.allclose(tk.pose_xy[1, 10], [tr.x_m[1, 50], tr.y_m[1, 50]])


def test_matching_a_history_then_padding_equals_matching_the_window(vocab):
    """The online driver matches only the 11 history states and pads (TokenizedAgents.padded_to): the same arrays as
    matching a full window whose later states are invalid."""
    tr = bicycle_tracks(4, seed=3)
    tr.valid[:, 11:] = False
    tr.valid[0, :4] = False  # a late-appearing agent
    full = match_agents(tr, vocab)
    short = match_agents(tr.slice_steps(0, 11), vocab).padded_to(N_POSE)
    for f in full.FIELDS:
        assert np.array_equal(getattr(full, f), getattr(short, f)), f
    assert (short.token[1:, :2] >= 0).all() and (short.token[:, 2:] == -1).all()
    with pytest.raises(ValueError, match="fewer"):
        full.padded_to(3)


def test_build_vocab_from_dataset_report():
    scen = [Scenario(bicycle_tracks(10, seed=s), straight_map()) for s in range(4)]
    cfg = VocabBuildConfig(size=(256, 32, 32), tolerance_m=0.05, min_real_segments=500, n_synthetic=5000, heldout_fraction=0.25)
    vocab, report = build_vocab_from_dataset(scen, cfg)
    assert report["vehicle/n_agents"] == 10 and report["all/horizon_s"] == 8.0
    # a small vocabulary from 30 tracks: sub-metre on average (the fixture's 512 tokens reach < 0.5 m max)
    assert 0 < report["all/pos_err_mean_m"] < 1.0 and report["all/pos_err_mean_m"] < report["all/pos_err_max_m"]
    assert report["all/yaw_err_mean_deg"] < 10.0
    assert vocab.meta["report"] == report


# ---------------------------------------------------------------------------- map tokens


def test_map_tokens_lengths_frames_and_tl():
    curve = np.stack([20 * np.cos(np.linspace(0, np.pi / 2, 30)), 20 * np.sin(np.linspace(0, np.pi / 2, 30))], 1)
    lines = [curve, np.array([[0.0, 0.0], [2.0, 0.0]]), np.array([[5.0, 5.0], [5.0, 5.0]]), np.array([[0, 0], [10.0, 0], [10, 10]])]
    tls = np.zeros((4, T91), np.int8)
    tls[0] = np.arange(T91) % 4
    mp = MapPolylines.from_lists(lines, [0, 1, 0, 0], ["a", "b", "c", "d"], [10, 0, 5, 7], [3, 0, 3, 3], tls)
    mt = tokenize_map(mp)
    n = mt.pts.shape[1]
    assert n == 11
    seg_arc = np.linalg.norm(np.diff(mt.pts, axis=1), axis=-1).sum(1)  # [M]
    assert (seg_arc <= 5.0 + 1e-4).all()
    assert np.allclose(mt.pts[:, 0], 0.0, atol=1e-5) and np.allclose(mt.pts[:, -1, 1], 0.0, atol=1e-4)
    assert (mt.pts[:, -1, 0] > 0).all()
    # arc length of the quarter circle is covered by its tokens, 10 * pi / ... = 31.4 m -> 7 tokens
    arc = np.linalg.norm(np.diff(curve, axis=0), axis=1).sum()
    assert (mt.polyline == 0).sum() == int(np.ceil(arc / 5.0)) and np.isclose(seg_arc[mt.polyline == 0].sum(), arc, rtol=1e-3)
    # short polyline: one 2 m token; the zero-length polyline is dropped; the corner polyline keeps its corner
    assert (mt.polyline == 1).sum() == 1 and np.isclose(seg_arc[mt.polyline == 1][0], 2.0)
    assert (mt.polyline == 2).sum() == 0 and (mt.polyline == 3).sum() == 4
    assert np.allclose(mt.world_points()[mt.polyline == 3][1, -1], [10.0, 0.0], atol=1e-4)
    assert np.allclose(mt.world_points()[:, 0], mt.pos, atol=1e-5)
    assert np.isclose(mt.yaw[mt.polyline == 1][0], 0.0) and np.isclose(mt.yaw[mt.polyline == 3][2], np.pi / 2, atol=1e-5)
    assert (mt.kind[mt.polyline == 1] == 1).all() and (mt.speed_limit_mps[mt.polyline == 3] == 7).all()
    assert mt.tl.shape == (mt.num_tokens, N_POSE)
    assert np.array_equal(mt.tl[mt.polyline == 0][0], tls[0, ::5]) and (mt.tl[mt.polyline != 0] == 0).all()
    assert (tokenize_map(mp.with_tl_state(np.zeros((4, 0), np.int8))).tl == 0).all()


# ---------------------------------------------------------------------------- scenes and batches


def test_tokenize_scenario_window_crop_and_collate(vocab):
    s1 = Scenario(bicycle_tracks(5, seed=2), straight_map(length_m=1000.0), metadata={"scenario_id": "s1"})
    s1.agents.x_m[:] = np.clip(s1.agents.x_m, -100, 100)
    hist = bicycle_tracks(3, n_steps=11, seed=3)  # a live state: history only, future unknown
    s2 = Scenario(hist, straight_map(tl=False))
    full = tokenize_scenario(s1, vocab, map_radius_m=None)
    cropped = tokenize_scenario(s1, vocab, map_radius_m=150.0)
    assert 0 < cropped.map.num_tokens < full.map.num_tokens
    cur = cropped.agents.pose_xy[:, CURRENT_POSE]
    far = ~full.map.within(cur, 150.0)
    assert far.any() and cropped.map.num_tokens == (~far).sum()
    live = tokenize_scenario(s2, vocab)
    assert live.agents.pose_valid[:, : CURRENT_POSE + 1].all() and not live.agents.pose_valid[:, CURRENT_POSE + 1:].any()
    assert (live.agents.token[:, CURRENT_POSE:] == -1).all()

    b = collate([cropped, live])
    A, M = 5, max(cropped.map.num_tokens, live.map.num_tokens)
    assert b.agent_token.shape == (2, A, N_TOK) and b.agent_token.dtype == torch.int64
    assert b.pose_xy.shape == (2, A, N_POSE, 2) and b.pose_xy.dtype == torch.float32
    assert b.map_pts.shape == (2, M, 11, 2) and b.map_tl.shape == (2, M, N_POSE)
    assert b.agent_mask[0].all() and b.agent_mask[1].sum() == 3
    assert (b.agent_token[1, 3:] == -1).all() and not b.pose_valid[1, 3:].any() and not b.agent_token_valid[1, 3:].any()
    assert b.map_mask[0].sum() == cropped.map.num_tokens and b.map_mask[1].sum() == live.map.num_tokens
    assert torch.equal(b.agent_size[0, :, 0], torch.from_numpy(cropped.agents.length_m))
    assert (b.map_pts[~b.map_mask] == 0).all() and (b.agent_type[~b.agent_mask] == 0).all()


def test_tokenized_dataset_cache(vocab, tmp_path):
    write_dataset(tmp_path / "data", [Scenario(bicycle_tracks(4, seed=s), straight_map()) for s in range(3)])
    ds = TokenizedDataset(tmp_path / "data", vocab, cache_dir=tmp_path / "cache")
    direct = ds[1]
    assert (tmp_path / "cache" / "scene-00000001.npz").exists()
    cached = ds[1]
    for f in ("token", "pose_xy", "pose_valid"):
        assert np.array_equal(getattr(cached.agents, f), getattr(direct.agents, f))
    assert np.array_equal(cached.map.pts, direct.map.pts) and cached.scenario_id == direct.scenario_id
    assert ds.precompute(progress=False) == 2
    batch = collate([ds[i] for i in range(len(ds))])
    assert batch.agent_mask.sum() == 12
    other = MotionVocab.from_traj({t: vocab.traj[t][:-1] for t in (VEHICLE, CYCLIST, PEDESTRIAN)})
    with pytest.raises(ValueError, match="vocab_fingerprint"):
        TokenizedDataset(ScenarioDataset(tmp_path / "data"), other, cache_dir=tmp_path / "cache")


def test_vocab_command(tmp_path, capsys):
    from r1sim_sumo.cli import main

    write_dataset(tmp_path / "data", [Scenario(bicycle_tracks(6, seed=s), straight_map()) for s in range(3)])
    rc = main(["vocab", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "v.safetensors"),
               "--size", "128", "16", "16", "--tolerance", "0.1", "--heldout", "0.34"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "pos_err_mean_m" in out and "fingerprint" in out
    v = MotionVocab.load(tmp_path / "v.safetensors")
    assert v.sizes[1] <= 16 and v.meta["report"]["all/n_agents"] == 6


def test_box_corners_consistent_with_vocab():
    """Token corners are geometry.box_corners of the token poses with the type's fixed box."""
    traj = synthetic_segments(CYCLIST, 4, seed=0)
    c = segment_corners(traj, CYCLIST)
    assert np.allclose(c, box_corners(traj[..., 0], traj[..., 1], traj[..., 2], 2.0, 1.0), atol=1e-6)


def test_vocab_reconstructs_straight_motorway_driving_exactly(vocab):
    """Straight driving at any speed must stay straight in token space: with only data-driven k-disk tokens a
    vehicle at 30 m/s zig-zagged by about a metre after rolling matching (and drove off motorway lanes)."""
    from r1sim_sumo.tokens.matching import match_agents, reconstruct_states

    speeds = np.array([3.0, 14.0, 23.7, 31.3])  # [m/s]
    T = 91
    t = np.arange(T) * 0.1
    yaw0 = np.array([0.0, 0.7, -2.0, 3.0])
    x = 100.0 + np.cos(yaw0)[:, None] * speeds[:, None] * t
    y = -50.0 + np.sin(yaw0)[:, None] * speeds[:, None] * t
    tr = bicycle_tracks(4, n_steps=T, seed=0)
    tr.x_m, tr.y_m = x, y
    tr.yaw_rad = np.repeat(yaw0[:, None], T, 1)
    tr.valid = np.ones((4, T), bool)
    tk = match_agents(tr, vocab)
    xy, _ = reconstruct_states(torch.from_numpy(tk.pose_xy[:, 0]).double(), torch.from_numpy(tk.pose_yaw[:, 0]).double(),
                               torch.from_numpy(tk.token), vocab, torch.from_numpy(tk.agent_type))
    # lateral error (perpendicular to the direction of travel) over 9 s
    lat = -np.sin(yaw0)[:, None] * (xy[..., 0].numpy() - x) + np.cos(yaw0)[:, None] * (xy[..., 1].numpy() - y)
    assert np.abs(lat).max() < 0.02, np.abs(lat).max(1)
    assert vocab.meta["n_kinematic_grid_tokens"]["vehicle"] > 0


def test_many_agents_match_through_a_kdtree_to_the_same_tokens(vocab, monkeypatch):
    """From TREE_MIN_ROWS agents per step the prefilter queries a k-d tree; it picks the tokens the matmul picks."""
    import r1sim_sumo.tokens.matching as matching

    end_corners, _, end_sq = matching._end_tables(vocab)
    E = end_corners[0]
    rng = np.random.default_rng(0)
    g = E[rng.integers(0, E.shape[0], 3000)] + torch.from_numpy(rng.normal(0, 0.4, (3000, 4, 2)).astype(np.float32))
    assert len(g) >= matching.TREE_MIN_ROWS
    tree, _ = matching._nearest_token(g, E, end_sq[0])
    monkeypatch.setattr(matching, "TREE_MIN_ROWS", 10**9)
    mat, _ = matching._nearest_token(g, E, end_sq[0])
    dist = lambda tok: (E[tok] - g).square().sum(-1).sqrt().mean(-1)  # noqa: E731
    assert (tree == mat).mean() >= 0.999
    assert (dist(tree) <= dist(mat) + 1e-5).all()  # where a near-tie differs, the tree's token is no farther
