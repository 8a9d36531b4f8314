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


def merge_map():
    """An acceleration lane ``acc_0`` (y = 0, x 0..200 m, ends) beside ``acc_1`` (y = 3.5 m) that goes on to
    ``main_0``; ``exit_0`` ends with no sibling (a network exit, not a must-merge lane)."""
    import numpy as np

    from r1sim_sumo.scenario import MapPolylines

    def seg(x0, x1, y):
        return np.stack([np.linspace(x0, x1, 5), np.full(5, y)], 1)

    return MapPolylines.from_lists([seg(0, 200, 0.0), seg(0, 200, 3.5), seg(200, 400, 3.5), seg(-100, 0, -30.0)],
                                   [0, 0, 0, 0], ["acc_0", "acc_1", "main_0", "exit_0"], [30.0] * 4, [3.5] * 4,
                                   successors=[(1, 2)])


def test_must_merge_lanes_are_lanes_that_end_beside_one_that_goes_on():
    import numpy as np

    from r1sim_sumo.metrics.lane_changes import must_merge_lanes, poses_on_lanes

    m = merge_map()
    assert must_merge_lanes(m) == [0]
    xy = np.array([[50.0, 0.5], [50.0, 3.4], [50.0, -0.3], [250.0, 3.5]])
    on = poses_on_lanes(m, [0], xy, np.array([0.0, 0.0, np.pi, 0.0]))
    assert on.tolist() == [True, False, False, False]  # the third heads the wrong way


def test_must_merge_weight_scales_the_rewards_of_agents_on_a_lane_that_ends():
    m = merge_map()
    r = hand_result([[[x, 0.0] for x, _ in line(50, 60)], [[x, 3.5] for x, _ in line(50, 60)]])
    b = ref_batch_for(r, [[[50, 0], [60, 0]], [[50, 3.5], [60, 3.5]]])
    pxy = b.pose_xy.clone()
    pxy[0, 0, :3] = torch.tensor([50.0, 0.0])
    pxy[0, 1, :3] = torch.tensor([50.0, 3.5])
    b = b._replace(pose_xy=pxy)
    plain = compute_rewards(r, b, RewardConfig(offroad=True), maps=[m])
    weighted = compute_rewards(r, b, RewardConfig(offroad=True, must_merge_weight=3.0), maps=[m])
    assert float(plain.reward[0, 0, 0, 0]) > 0
    assert torch.allclose(weighted.reward[0, 0, 0], 3.0 * plain.reward[0, 0, 0])
    assert torch.equal(weighted.reward[0, 0, 1], plain.reward[0, 0, 1])
    with pytest.raises(ValueError, match="maps"):
        compute_rewards(r, b, RewardConfig(must_merge_weight=3.0))


class _FakePart:
    """What ``must_merge_scenes`` reads of a compact token dataset: per-agent logged poses, scene -> map, the maps."""

    def __init__(self, scenes, maps):
        import numpy as np

        from r1sim_sumo.tokens.constants import N_POSE

        n_agents = [len(agents) for _, agents in scenes]
        xy = np.array([p for _, agents in scenes for p in agents], np.float32).reshape(-1, 2)
        self.a = {"n_agents": np.array(n_agents), "map_of_scene": np.array([k for k, _ in scenes]),
                  "gt_x": np.repeat(xy[:, :1], N_POSE, 1), "gt_y": np.repeat(xy[:, 1:], N_POSE, 1),
                  "gt_yaw": np.zeros((len(xy), N_POSE), np.float32), "gt_valid": np.ones((len(xy), N_POSE), bool)}
        self.maps = maps

    def __len__(self):
        return len(self.a["n_agents"])

    def polylines(self, i):
        return self.maps[int(self.a["map_of_scene"][i])]


def test_scene_focus_keeps_the_scenes_with_an_agent_on_a_must_merge_lane():
    from types import SimpleNamespace

    from r1sim_sumo.train.grpo import FocusedSource, GRPOConfig, must_merge_scenes
    from tests.test_grpo import one_lane_map

    merge, plain = merge_map(), one_lane_map()
    # part 0: scene 0 has an agent on acc_0; scene 1 only on acc_1; scene 2 is on a map without a must-merge lane
    p0 = _FakePart([(0, [[20.0, 3.5], [120.0, 0.2]]), (0, [[20.0, 3.5]]), (1, [[0.0, 0.0]])], [merge, plain])
    p1 = _FakePart([(0, [[190.0, -0.4]]), (0, [[300.0, 3.5]])], [merge])  # joined indices 3, 4
    assert must_merge_scenes(SimpleNamespace(parts=[p0, p1])).tolist() == [0, 3]
    inner = SimpleNamespace(batch=lambda idx: idx, maps=lambda idx: idx)
    focused = FocusedSource(inner, [0, 3])
    assert len(focused) == 2 and focused.batch([1, 0]) == [3, 0] and focused.maps([1]) == [3]
    with pytest.raises(ValueError, match="train_tokens"):
        GRPOConfig(scene_focus="must-merge")
    with pytest.raises(ValueError, match="scene_focus"):
        GRPOConfig(scene_focus="merges")
    with pytest.raises(ValueError, match="offroad"):
        GRPOConfig(reward={"must_merge_weight": 2.0})
    with pytest.raises(ValueError, match="no scene"):
        FocusedSource(None, [])
