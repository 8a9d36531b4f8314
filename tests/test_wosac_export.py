"""The WOSAC exporter's torch-free parts: bundles, held poses, road-edge orientation, errors, the CLI entry."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

pytest.importorskip("shapely")

from r1sim_sumo.metrics.types import SimTrajectories  # noqa: E402
from r1sim_sumo.scenario import LANE_CENTRE, AgentTracks, MapPolylines, Scenario  # noqa: E402
from r1sim_sumo.wosac_export import (  # noqa: E402
    WosacExportError,
    _held,
    load_bundle,
    road_edge_rings,
    save_bundle,
    sim_agent_mask,
)


def _scene(T: int = 91) -> Scenario:
    mp = MapPolylines.from_lists([np.array([[-50.0, 0.0], [250.0, 0.0]])], [LANE_CENTRE], ["l0"], [30.0], [3.5])
    tr = AgentTracks.empty(3, T)
    t = np.arange(T) * 0.1
    tr.x_m = np.stack([10 * t, 10 * t + 20, 10 * t + 40]).astype(np.float32)
    tr.vx_mps = np.full((3, T), 10.0, np.float32)
    tr.speed_mps = np.full((3, T), 10.0, np.float32)
    tr.valid = np.ones((3, T), bool)
    tr.valid[2, :40] = False  # enters later: not a sim agent
    for f in AgentTracks.PER_STEP:
        getattr(tr, f)[~tr.valid] = 0.0
    tr.length_m = np.full(3, 4.5, np.float32)
    tr.width_m = np.full(3, 1.8, np.float32)
    return Scenario(tr, mp, {"source": "test"}).validate()


def test_bundle_roundtrip(tmp_path):
    sc = _scene()
    sim = SimTrajectories.log_replay(sc, 4)
    save_bundle(tmp_path, "s1", sc, sim)
    sid, sc2, sim2 = load_bundle(tmp_path / "s1.scenario.npz")
    assert sid == "s1" and sc2.agents.num_agents == 3
    np.testing.assert_allclose(sim2.x_m, sim.checked(sc).x_m)
    assert sim_agent_mask(sc2).tolist() == [True, True, False]
    (tmp_path / "s1.rollouts.npz").unlink()
    with pytest.raises(WosacExportError, match="rollouts"):
        load_bundle(tmp_path / "s1.scenario.npz")


def test_invalid_rollout_steps_hold_the_last_valid_pose():
    v = np.array([[[True, False, False, True, False]]])
    x = np.array([[[1.0, 9.0, 9.0, 4.0, 9.0]]])
    assert _held(x, v, np.array([0.5])).tolist() == [[[1.0, 1.0, 1.0, 4.0, 4.0]]]
    assert _held(x, ~v, np.array([0.5])).tolist() == [[[0.5, 9.0, 9.0, 9.0, 9.0]]]


def test_road_edges_wind_with_the_road_on_the_left():
    """WOSAC's road edges keep the road on the port (left) side: a point a little left of every edge segment is inside
    our drivable area, one a little right of it is outside."""
    import shapely

    from r1sim_sumo.metrics.map_features import drivable_area

    sc = _scene()
    rings = road_edge_rings(sc)
    area = drivable_area(sc.map).polygon
    assert rings
    for ring in rings:
        a, b = ring[:-1], ring[1:]
        d = b - a
        n = np.linalg.norm(d, axis=1)
        keep = n > 0.05
        mid = (a + b)[keep] / 2
        left = np.stack([-d[keep, 1], d[keep, 0]], 1) / n[keep, None]
        assert shapely.contains_xy(area, *(mid + 0.05 * left).T).all()
        assert not shapely.contains_xy(area, *(mid - 0.05 * left).T).any()


@pytest.mark.skipif(importlib.util.find_spec("waymo_open_dataset") is not None, reason="the official package is installed")
def test_protos_need_the_official_package_and_say_how_to_get_it():
    from r1sim_sumo.wosac_export import scenario_to_proto

    with pytest.raises(ImportError, match="waymo-open-dataset-tf-2-12-0==1.6.7"):
        scenario_to_proto(_scene(), "s1")


def test_export_wosac_is_a_cli_subcommand():
    from r1sim_sumo.cli import build_parser

    args = build_parser().parse_args(["export-wosac", "--data", "d", "--out", "o", "--scenes", "1,2"])
    assert args.scenes == "1,2" and args.rollouts == 32
