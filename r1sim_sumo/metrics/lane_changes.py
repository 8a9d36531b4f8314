"""Lane changes read from trajectories alone (no map): which agents move sideways by a lane while keeping their heading.

A trajectory changes lanes when, in the frame of its start pose (box centre, x along the heading), some later valid
pose lies at least ``LANE_CHANGE_OFFSET_M`` to the side while its heading is within ``STRAIGHT_YAW_RAD`` of the start
heading, and no later valid pose turns away by more than ``TURN_YAW_RAD`` (a junction turn or a curve moves sideways
too; those are not lane changes). On the networks of this project lanes are 3.2-3.75 m wide, so 2.5 m sideways with an
unchanged heading is a vehicle that has crossed into the next lane (or most of the way).

Used by the GRPO reward (``RewardConfig.lane_change_weight``: weight the agents whose reference changes lanes) and by
``scripts/eval_lane_changes.py`` (closed loop: how often the policy changes lanes where the log did).
"""

from __future__ import annotations

import math

import torch

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
    dyaw = torch.remainder(yaw - start_yaw.unsqueeze(-1) + math.pi, 2 * math.pi) - math.pi
    ok = valid.bool() & start_valid.bool().unsqueeze(-1)
    hit = ok & (lateral.abs() >= LANE_CHANGE_OFFSET_M) & (dyaw.abs() < STRAIGHT_YAW_RAD)
    turns = (ok & (dyaw.abs() > TURN_YAW_RAD)).any(-1)
    first = torch.argmax(hit.to(torch.int8), dim=-1, keepdim=True)  # first True (0 when none: masked below)
    side = torch.sign(torch.gather(lateral, -1, first).squeeze(-1)).to(torch.int64)
    return torch.where(hit.any(-1) & ~turns, side, torch.zeros_like(side))
