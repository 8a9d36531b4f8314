"""Extending a vehicle vocabulary with exact high-speed curve and lane-change tokens, keeping every existing id.

Why: the data-driven k-disk of :mod:`~r1sim_sumo.tokens.motion_vocab` spends its budget at urban speeds. At
motorway speeds (10-20 m of displacement per 0.5 s token) the shipped 2048-token vehicle vocabulary holds ~20
tokens per metre of displacement, with end headings 0 and +-2 degrees but none between, and lateral offsets that
do not reach a lane change's (0.5-1.5 m per token at 25 m/s). Rolling matching of a vehicle on a gentle curve then
drifts 1-4 m sideways and a lane change lags up to a lane width: the logged futures rebuilt from their own tokens
leave the road on 9.4% of lane_drop's agents (``docs/training/token_floor.md``), a floor no policy over that
vocabulary gets under.

Two families of exact 0.5 s segments (start-pose frame: x forward, y left [m], yaw [rad] CCW) are appended to the
vehicle vocabulary (ids from its old size on; cyclist and pedestrian vocabularies unchanged):

* :func:`curve_segments`: constant speed and curvature, end heading changes of a few tenths of a degree to a few
  degrees, every 0.5 m of displacement from 5 to 20 m (10-40 m/s);
* :func:`lane_change_segments`: cubic paths that start straight (heading 0) and end ``lat`` metres to the side with
  end heading ``yaw_end`` (the phases of a lane change: leaving, crossing, arriving), every metre from 8 to 20 m.

A candidate is dropped when the vocabulary (old tokens or candidates already kept) has a token whose end position
is within ``min_end_m`` and end heading within ``min_end_yaw_deg`` (matching compares end poses, so such a token
would never be chosen over it). Deterministic: the same vocabulary in gives the same one out.
"""

from __future__ import annotations

import math

import numpy as np

from r1sim_sumo.tokens.constants import FRAMES_PER_TOKEN as FRAMES
from r1sim_sumo.tokens.motion_vocab import VEHICLE, MotionVocab, constant_curvature_segments

CURVE_DISPLACEMENTS_M = np.arange(5.0, 20.0 + 1e-9, 0.5)  # [m] per 0.5 s token: 10 .. 40 m/s
CURVE_HEADINGS_DEG = (0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 2.5)  # end heading changes, both signs
LANE_CHANGE_DISPLACEMENTS_M = np.arange(8.0, 20.0 + 1e-9, 1.0)  # [m]: 16 .. 40 m/s
LANE_CHANGE_OFFSETS_M = np.round(np.arange(-1.5, 1.5 + 1e-9, 0.2), 3)  # [m] lateral offset at the end (+ = left)
LANE_CHANGE_END_HEADINGS_DEG = (-6, -4, -2, 0, 2, 4, 6)


def curve_segments(displacements_m=CURVE_DISPLACEMENTS_M, headings_deg=CURVE_HEADINGS_DEG) -> np.ndarray:
    """``[n, 6, 3]`` constant-speed, constant-curvature segments: arc length ``d`` [m], end heading ``+-h`` [deg]."""
    rows = [(d, math.radians(s * h)) for d in displacements_m for h in headings_deg for s in (1, -1)]
    return constant_curvature_segments([r[0] for r in rows], [r[1] for r in rows])


def lane_change_segments(displacements_m=LANE_CHANGE_DISPLACEMENTS_M, offsets_m=LANE_CHANGE_OFFSETS_M,
                         end_headings_deg=LANE_CHANGE_END_HEADINGS_DEG) -> np.ndarray:
    """``[n, 6, 3]`` cubic paths ``y(x) = a x^2 + b x^3`` from the start pose (heading 0) to ``(d, lat)`` with end
    heading ``yaw_end``; frames evenly spaced in x (constant forward speed ``d / 0.5 s``)."""
    rows = [(d, lat, math.radians(h)) for d in displacements_m for lat in offsets_m for h in end_headings_deg]
    d = np.array([r[0] for r in rows])[:, None]
    lat = np.array([r[1] for r in rows])[:, None]
    m1 = np.tan(np.array([r[2] for r in rows]))[:, None]
    a, b = (3.0 * lat - m1 * d) / d**2, (m1 * d - 2.0 * lat) / d**3
    x = d * (np.arange(FRAMES)[None] / (FRAMES - 1))
    y = a * x**2 + b * x**3
    return np.stack([x, y, np.arctan(2.0 * a * x + 3.0 * b * x**2)], -1).astype(np.float32)


def extend_vehicle_vocab(vocab: MotionVocab, candidates: np.ndarray | None = None, min_end_m: float = 0.05,
                         min_end_yaw_deg: float = 0.3) -> MotionVocab:
    """``vocab`` with the new vehicle tokens of ``candidates [n, 6, 3]`` (default: :func:`curve_segments` then
    :func:`lane_change_segments`) appended; old ids keep their meaning. ``meta["extension"]`` records how many
    were added and from which vocabulary."""
    if candidates is None:
        candidates = np.concatenate([curve_segments(), lane_change_segments()])
    old = vocab.traj[VEHICLE]
    ends = np.empty((len(old) + len(candidates), 3))  # end poses of the tokens so far, old ones first
    ends[: len(old)] = old[:, -1]
    n, kept = len(old), []
    for seg in candidates:
        e = seg[-1].astype(np.float64)
        have = ends[:n]
        near = (np.hypot(have[:, 0] - e[0], have[:, 1] - e[1]) < min_end_m) & (
            np.degrees(np.abs(have[:, 2] - e[2])) < min_end_yaw_deg)
        if near.any():
            continue
        kept.append(seg)
        ends[n] = e
        n += 1
    traj = dict(vocab.traj)
    traj[VEHICLE] = np.concatenate([old, np.asarray(kept, np.float32).reshape(-1, FRAMES, 3)])
    meta = dict(vocab.meta)
    meta["extension"] = {"base_fingerprint": vocab.fingerprint(), "base_vehicle_size": int(len(old)),
                         "added_vehicle_tokens": len(kept), "families": "curve_segments + lane_change_segments",
                         "min_end_m": min_end_m, "min_end_yaw_deg": min_end_yaw_deg}
    return MotionVocab.from_traj(traj, meta)


def nearest_old_token(vocab: MotionVocab, base_size: int) -> np.ndarray:
    """For every vehicle token id ``>= base_size`` the nearest id ``< base_size`` by mean end-corner distance
    (``[n_new]`` int64): where an extended model starts the new tokens' weights from."""
    c = vocab.corners[VEHICLE][:, -1].reshape(len(vocab.traj[VEHICLE]), -1).astype(np.float64)  # [V, 8]
    old, new = c[:base_size], c[base_size:]
    out = np.empty(len(new), np.int64)
    for i in range(0, len(new), 256):
        d = np.sqrt(((new[i:i + 256, None, :].reshape(-1, 1, 4, 2) - old[None].reshape(1, -1, 4, 2)) ** 2).sum(-1)).mean(-1)
        out[i:i + 256] = d.argmin(1)
    return out
