"""Lane changes read from trajectories alone (no map): which agents move sideways by a lane while keeping their heading.

A trajectory changes lanes when, in the frame of its start pose (box centre, x along the heading), some later valid
pose lies at least ``LANE_CHANGE_OFFSET_M`` to the side while its heading is within ``STRAIGHT_YAW_RAD`` of the start
heading, and no later valid pose turns away by more than ``TURN_YAW_RAD`` (a junction turn or a curve moves sideways
too; those are not lane changes). On the networks of this project lanes are 3.2-3.75 m wide, so 2.5 m sideways with an
unchanged heading is a vehicle that has crossed into the next lane (or most of the way).

Used by the GRPO reward (``RewardConfig.lane_change_weight``: weight the agents whose reference changes lanes) and by
``scripts/eval_lane_changes.py`` (closed loop: how often the policy changes lanes where the log did).

A lane that ends beside a lane of the same edge that goes on (motorway_merge's acceleration lane ``merge_0``) is a
*must-merge* lane (:func:`must_merge_lanes`): a vehicle on it has to change lanes. ``GRPOConfig.scene_focus:
must-merge`` trains on the scenes with an agent on one, ``RewardConfig.must_merge_weight`` weights those agents.
"""

from __future__ import annotations

import numpy as np
import torch

from r1sim_sumo.geometry import wrap_angle

LANE_CHANGE_OFFSET_M = 2.5
"""Sideways offset [m] from the start pose's heading line that counts as a lane change."""
STRAIGHT_YAW_RAD = 0.15
"""Heading difference [rad] to the start heading within which a sideways offset is a lane change (~8.6 deg)."""
TURN_YAW_RAD = 0.3
"""Heading difference [rad] to the start heading beyond which the trajectory turns (no lane change counted)."""


def lane_change_direction(xy: torch.Tensor, yaw: torch.Tensor, valid: torch.Tensor, start_xy: torch.Tensor,
                          start_yaw: torch.Tensor, start_valid: torch.Tensor) -> torch.Tensor:
    """Per trajectory: +1 a lane change to the left, -1 to the right, 0 none (or no valid start pose).

    :param xy: ``[..., T, 2]`` later positions [m] (box centre, world frame).
    :param yaw: ``[..., T]`` their headings [rad, counter-clockwise from +x].
    :param valid: ``[..., T]`` bool, which of them exist.
    :param start_xy: ``[..., 2]`` start position [m]; ``start_yaw`` ``[...]`` [rad]; ``start_valid`` ``[...]`` bool.
    :returns: ``[...]`` int64 in {-1, 0, +1}; the side of the first pose that meets the offset.
    """
    d = xy - start_xy.unsqueeze(-2)
    c, s = torch.cos(start_yaw).unsqueeze(-1), torch.sin(start_yaw).unsqueeze(-1)
    lateral = -d[..., 0] * s + d[..., 1] * c  # [..., T] metres, + to the left of the start heading
    dyaw = wrap_angle(yaw - start_yaw.unsqueeze(-1))
    ok = valid.bool() & start_valid.bool().unsqueeze(-1)
    hit = ok & (lateral.abs() >= LANE_CHANGE_OFFSET_M) & (dyaw.abs() < STRAIGHT_YAW_RAD)
    turns = (ok & (dyaw.abs() > TURN_YAW_RAD)).any(-1)
    first = torch.argmax(hit.to(torch.int8), dim=-1, keepdim=True)  # first True (0 when none: masked below)
    side = torch.sign(torch.gather(lateral, -1, first).squeeze(-1)).to(torch.int64)
    return torch.where(hit.any(-1) & ~turns, side, torch.zeros_like(side))


def must_merge_lanes(m) -> list[int]:
    """Polyline indices of ``m``'s lanes that end beside a lane of the same edge that goes on
    (:meth:`~r1sim_sumo.scenario.MapPolylines.ending_lanes`)."""
    return m.ending_lanes()


def poses_on_lanes(m, lanes: list[int], xy: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """``[A]`` bool: the pose (``xy [A, 2]`` m, ``yaw [A]`` rad) lies within half the lane's width + 0.3 m of one of
    ``lanes``' centrelines, heading within 0.5 rad of the segment's."""
    out = np.zeros(len(xy), bool)
    for j in lanes:
        pts = m.points_m[m.start[j]: m.start[j + 1]].astype(np.float64)
        a, d = pts[:-1], pts[1:] - pts[:-1]
        seg2 = np.maximum((d ** 2).sum(1), 1e-9)
        t = np.clip((((xy[:, None, :] - a[None]) * d[None]).sum(-1)) / seg2[None], 0.0, 1.0)  # [A, S]
        dist = np.linalg.norm(xy[:, None, :] - (a[None] + t[..., None] * d[None]), axis=-1)
        near = dist.argmin(1)
        seg_yaw = np.arctan2(d[near, 1], d[near, 0])
        dyaw = np.abs(wrap_angle(yaw - seg_yaw))
        out |= (dist.min(1) <= 0.5 * float(m.width_m[j]) + 0.3) & (dyaw < 0.5)
    return out
