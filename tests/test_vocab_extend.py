"""Vocabulary extension with high-speed curve and lane-change tokens, and carrying a model over to it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_evaluate import curved_scene

from r1sim_sumo.model.resize_vocab import extend_policy_vocab, group_log_prob_gap
from r1sim_sumo.model.untrained import untrained_policy
from r1sim_sumo.scenario import AgentTracks
from r1sim_sumo.tokens.batch import collate, tokenize_scenario
from r1sim_sumo.tokens.matching import match_agents, reconstruct_states
from r1sim_sumo.tokens.motion_vocab import CYCLIST, PEDESTRIAN, VEHICLE, MotionVocab
from r1sim_sumo.tokens.vocab_extend import (
    curve_segments,
    extend_vehicle_vocab,
    lane_change_segments,
    nearest_old_token,
)


def test_curve_segments_are_exact_arcs():
    seg = curve_segments(displacements_m=[12.5], headings_deg=[0.5])  # [2, 6, 3]: +0.5 and -0.5 degrees
    assert seg.shape == (2, 6, 3)
    np.testing.assert_allclose(np.degrees(seg[:, -1, 2]), [0.5, -0.5], atol=1e-5)
    step = np.hypot(*np.diff(seg[0, :, :2], axis=0).T)  # constant speed: equal chords
    np.testing.assert_allclose(step, 12.5 / 5, rtol=1e-4)
    assert seg[0, -1, 1] > 0 > seg[1, -1, 1]  # + = left


def test_lane_change_segments_start_straight_and_end_where_asked():
    seg = lane_change_segments(displacements_m=[12.0], offsets_m=[0.9], end_headings_deg=[2])
    (s,) = seg
    assert s[0, 2] == pytest.approx(0.0, abs=1e-7) and s[-1, 0] == pytest.approx(12.0)
    assert s[-1, 1] == pytest.approx(0.9, abs=1e-5) and math.degrees(s[-1, 2]) == pytest.approx(2.0, abs=1e-4)


def _motorway_track(kind: str) -> AgentTracks:
    """One car at 25 m/s for 9 s: on a 450 m-radius curve, or changing lanes (3.5 m left over 2 s) on a straight."""
    t = np.arange(91) * 0.1
    a = AgentTracks.empty(1, 91)
    if kind == "curve":
        R, v = 450.0, 25.0
        phi = v / R * t
        a.x_m[0], a.y_m[0], a.yaw_rad[0] = R * np.sin(phi), R * (1 - np.cos(phi)), phi
    else:
        x = 25.0 * t
        u = np.clip((t - 3.0) / 2.0, 0, 1)
        y = 3.5 * (3 * u**2 - 2 * u**3)
        dy = np.gradient(y, t)
        a.x_m[0], a.y_m[0], a.yaw_rad[0] = x, y, np.arctan2(dy, 25.0)
    a.speed_mps[0] = 25.0
    a.valid[:] = True
    a.length_m[:], a.width_m[:] = 4.8, 2.0
    return a


def _lateral_drift(vocab: MotionVocab, tracks: AgentTracks) -> float:
    tk = match_agents(tracks, vocab)
    xy, _ = reconstruct_states(torch.from_numpy(tk.pose_xy[None, :, 0]), torch.from_numpy(tk.pose_yaw[None, :, 0]),
                               torch.from_numpy(tk.token[None]), vocab, torch.from_numpy(tk.agent_type[None]))
    xy = xy[0, 0].numpy()  # [91, 2]
    yaw = tracks.yaw_rad[0]
    d = xy - np.stack([tracks.x_m[0], tracks.y_m[0]], -1)
    return float(np.abs(-np.sin(yaw) * d[:, 0] + np.cos(yaw) * d[:, 1]).max())


@pytest.mark.parametrize("kind", ["curve", "lane_change"])
def test_extension_keeps_old_ids_and_follows_motorway_motion(kind):
    """A sparse high-speed vocabulary (the synthetic one of the untrained policy) rebuilds a 25 m/s curve or lane change
    with a lateral error the extended one cuts to a fraction, while every old token keeps its id."""
    base = untrained_policy(0).vocab
    ext = extend_vehicle_vocab(base)
    n_old = base.size(VEHICLE)
    assert ext.size(VEHICLE) > n_old and ext.meta["extension"]["added_vehicle_tokens"] == ext.size(VEHICLE) - n_old
    np.testing.assert_array_equal(ext.traj[VEHICLE][:n_old], base.traj[VEHICLE])
    for t in (CYCLIST, PEDESTRIAN):
        np.testing.assert_array_equal(ext.traj[t], base.traj[t])
    assert extend_vehicle_vocab(base).fingerprint() == ext.fingerprint()  # deterministic
    tr = _motorway_track(kind)
    before, after = _lateral_drift(base, tr), _lateral_drift(ext, tr)
    assert after < 0.3 and after < 0.5 * before, (before, after)


def test_extended_model_starts_with_the_old_distribution_over_token_groups():
    pol = untrained_policy(3)
    ext = extend_vehicle_vocab(pol.vocab)
    model = extend_policy_vocab(pol.model, pol.vocab, ext).eval()
    assert model.config.vocab_sizes[VEHICLE] == ext.size(VEHICLE)
    base = pol.vocab.size(VEHICLE)
    near = nearest_old_token(ext, base)
    assert near.min() >= 0 and near.max() < base
    scs = [curved_scene(s) for s in range(2)]
    b_old = collate([tokenize_scenario(sc, pol.vocab) for sc in scs])
    assert group_log_prob_gap(pol.model.eval(), model, b_old, base, near) < 1e-4
    with pytest.raises(ValueError, match="only the vehicle vocabulary"):
        bad = MotionVocab.from_traj({**ext.traj, CYCLIST: ext.traj[CYCLIST][:-1]})
        extend_policy_vocab(pol.model, pol.vocab, bad)
