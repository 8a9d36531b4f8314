"""Lane changes read from trajectories (r1sim_sumo.metrics.lane_changes) and the GRPO reward's lane-change weight."""

import math

import pytest
import torch

from r1sim_sumo.metrics.lane_changes import lane_change_direction
from r1sim_sumo.train.rewards import RewardConfig, compute_rewards
from tests.test_grpo import hand_result, line, ref_batch_for


def _direction(points, yaws, start_yaw=0.0):
    xy = torch.tensor([points], dtype=torch.float32)
    yaw = torch.tensor([yaws], dtype=torch.float32)
    valid = torch.ones(1, len(points), dtype=torch.bool)
    return int(lane_change_direction(xy, yaw, valid, torch.zeros(1, 2), torch.tensor([start_yaw]), torch.ones(1, dtype=torch.bool))[0])


def test_a_sideways_move_with_the_heading_kept_is_a_lane_change_and_its_side_is_read():
    straight = [[10.0 * k, 0.0] for k in range(1, 9)]
    left = [[10.0 * k, min(3.2, 0.8 * k)] for k in range(1, 9)]
    right = [[10.0 * k, -min(3.2, 0.8 * k)] for k in range(1, 9)]
    assert _direction(straight, [0.0] * 8) == 0
    assert _direction(left, [0.05] * 8) == 1
    assert _direction(right, [-0.05] * 8) == -1
    # half a lane sideways is not a lane change
    assert _direction([[10.0 * k, 1.5] for k in range(1, 9)], [0.0] * 8) == 0
    # the same offsets in a rotated frame (heading 90 deg: "left" is -x)
    rot = [[-y, x] for x, y in left]
    assert _direction(rot, [math.pi / 2 + 0.05] * 8, start_yaw=math.pi / 2) == 1


def test_a_turn_is_not_a_lane_change():
    # a right turn: ends 20 m to the side heading -90 deg; at one pose on the way its heading is back near the start's
    turn = [[10.0, -0.5], [15.0, -3.0], [18.0, -8.0], [20.0, -14.0], [20.0, -20.0]]
    assert _direction(turn, [-0.1, -0.6, -1.2, -1.5, -1.57]) == 0


def test_invalid_poses_and_starts_count_for_nothing():
    xy = torch.tensor([[[10.0, 3.2], [20.0, 3.2]]])
    yaw = torch.zeros(1, 2)
    assert int(lane_change_direction(xy, yaw, torch.tensor([[False, False]]), torch.zeros(1, 2), torch.zeros(1),
                                     torch.ones(1, dtype=torch.bool))[0]) == 0
    assert int(lane_change_direction(xy, yaw, torch.ones(1, 2, dtype=torch.bool), torch.zeros(1, 2), torch.zeros(1),
                                     torch.zeros(1, dtype=torch.bool))[0]) == 0


def test_lane_change_weight_scales_the_rewards_of_agents_whose_reference_changes_lanes():
    # agent 0's reference changes lanes (0 -> 3.2 m sideways over two tokens), agent 1's drives straight on
    r = hand_result([line(0, 10) + line(10, 20)[1:], [[x, 10.0] for x, _ in line(0, 10) + line(10, 20)[1:]]])
    b = ref_batch_for(r, [[[0, 0], [10, 1.6], [20, 3.2]], [[0, 10], [10, 10], [20, 10]]])
    plain = compute_rewards(r, b, RewardConfig(kind="spr", alpha=0.2))
    weighted = compute_rewards(r, b, RewardConfig(kind="spr", alpha=0.2, lane_change_weight=4.0))
    assert torch.equal(plain.mask, weighted.mask)
    assert torch.allclose(weighted.reward[0, 0, 0], 4.0 * plain.reward[0, 0, 0])
    assert torch.equal(weighted.reward[0, 0, 1], plain.reward[0, 0, 1])
    assert float(plain.reward[0, 0, 0, 1]) == pytest.approx(math.exp(-0.2 * 3.2))
    with pytest.raises(ValueError, match="lane_change_weight"):
        RewardConfig(lane_change_weight=0.0)
