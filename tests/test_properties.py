"""Property-based tests (hypothesis): the scenario dataset round trip, validate() against random NaN injections,
the frame conversions of geometry.py and the SAT box-overlap check (symmetry, invariances, shapely agreement)."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import shapely
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from r1sim_sumo.geometry import (
    box_corners,
    boxes_overlap,
    centre_to_front_bumper,
    front_bumper_to_centre,
    highway_to_internal,
    internal_to_highway,
    sumo_angle_deg_to_yaw_rad,
    wrap_angle,
    yaw_rad_to_sumo_angle_deg,
)
from r1sim_sumo.reliability.fixtures import toy_scenario
from r1sim_sumo.scenario import AgentTracks, ScenarioDataset, ScenarioError, write_dataset

FAST = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
finite = dict(allow_nan=False, allow_infinity=False)
coords = st.floats(-5e3, 5e3, **finite)
yaws = st.floats(-math.pi, math.pi, exclude_max=True, **finite)


def _angle_close(a, b, tol=1e-9) -> bool:
    return abs(wrap_angle(a - b)) < tol


# ---------------------------------------------------------------------------- scenario loader


@st.composite
def valid_scenarios(draw):
    sc = toy_scenario(num_agents=draw(st.integers(1, 6)), seed=draw(st.integers(0, 10_000)))
    a = sc.agents
    A, T = a.valid.shape
    hole = draw(st.lists(st.tuples(st.integers(0, A - 1), st.integers(0, T - 1)), max_size=10))
    for i, t in hole:  # random invalid steps, never the whole track
        if a.valid[i].sum() > 1:
            a.valid[i, t] = False
            for f in AgentTracks.PER_STEP:
                getattr(a, f)[i, t] = 0.0
    a.yaw_rad[:] = np.where(a.valid, draw(st.floats(-3.0, 3.0, **finite)), 0.0)
    sc.metadata["note"] = draw(st.text(max_size=8))
    return sc


@FAST
@given(st.lists(valid_scenarios(), min_size=1, max_size=5), st.integers(1, 3))
def test_write_dataset_round_trip(scs, shard_size):
    with tempfile.TemporaryDirectory() as d:
        ds = ScenarioDataset(write_dataset(Path(d) / "ds", scs, shard_size=shard_size))
        assert len(ds) == len(scs)
        for i, (sc, back) in enumerate(zip(scs, ds, strict=True)):
            for f in AgentTracks.FIELDS:
                np.testing.assert_array_equal(np.asarray(getattr(sc.agents, f)), np.asarray(getattr(back.agents, f)), err_msg=f)
            np.testing.assert_array_equal(sc.map.points_m, back.map.points_m)
            assert back.metadata == sc.metadata and ds[i].current_index == sc.current_index


@FAST
@given(valid_scenarios(), st.sampled_from(AgentTracks.PER_STEP), st.data(), st.sampled_from([np.nan, np.inf, -np.inf]))
def test_validate_rejects_random_non_finite_injection(sc, field, data, bad):
    a = sc.agents
    cells = np.argwhere(a.valid)
    i, t = cells[data.draw(st.integers(0, len(cells) - 1))]
    getattr(a, field)[i, t] = bad
    try:
        sc.validate(source="inj.npz")
    except ScenarioError as exc:
        assert f"agents.{field}" in str(exc) and "inj.npz" in str(exc) and str(a.ids[i]) in str(exc)
    else:
        raise AssertionError(f"{field}[{i}, {t}] = {bad} accepted")


@FAST
@given(valid_scenarios(), st.data())
def test_validate_ignores_non_finite_at_invalid_steps(sc, data):
    a = sc.agents
    a.valid[0, 0] = False
    if not a.valid[0].any():
        a.valid[0, 1] = True
    a.x_m[0, 0] = data.draw(st.sampled_from([np.nan, np.inf]))
    assert sc.validate() is sc


# ---------------------------------------------------------------------------- frame conversions


@FAST
@given(coords, coords, yaws, st.floats(0.5, 20.0, **finite))
def test_sumo_front_bumper_nav_degrees_round_trip(x, y, yaw, length):
    xf, yf = centre_to_front_bumper(x, y, yaw, length)
    ang = yaw_rad_to_sumo_angle_deg(yaw)
    assert 0.0 <= ang < 360.0
    yaw2 = sumo_angle_deg_to_yaw_rad(ang)
    xc, yc = front_bumper_to_centre(xf, yf, yaw2, length)
    assert abs(xc - x) < 1e-6 and abs(yc - y) < 1e-6 and _angle_close(yaw2, yaw, 1e-9)
    assert abs(math.hypot(xf - x, yf - y) - length / 2) < 1e-6  # the bumper is half a length ahead


@FAST
@given(coords, coords, yaws)
def test_highway_env_y_down_round_trip(x, y, yaw):
    xh, yh, hh = internal_to_highway(x, y, yaw)
    assert yh == -y  # y-down
    x2, y2, yaw2 = highway_to_internal(xh, yh, hh)
    assert x2 == x and y2 == y and _angle_close(yaw2, yaw)


# ---------------------------------------------------------------------------- SAT box overlap

box = st.tuples(st.floats(-8, 8, **finite), st.floats(-8, 8, **finite), yaws, st.floats(0.3, 8, **finite), st.floats(0.3, 4, **finite))


def _clear(b1, b2, margin=1e-6) -> bool:
    """Not a near-touching case (the SAT test and shapely may disagree within float rounding)."""
    p1, p2 = shapely.polygons(box_corners(*map(np.float64, b1))), shapely.polygons(box_corners(*map(np.float64, b2)))
    return shapely.distance(p1, p2) > margin or shapely.area(shapely.intersection(p1, p2)) > margin


@FAST
@given(box, box)
def test_sat_symmetric_and_agrees_with_shapely(b1, b2):
    assume(_clear(b1, b2))
    ab, ba = bool(boxes_overlap(*b1, *b2)), bool(boxes_overlap(*b2, *b1))
    assert ab == ba
    truth = shapely.intersects(shapely.polygons(box_corners(*map(np.float64, b1))), shapely.polygons(box_corners(*map(np.float64, b2))))
    assert ab == bool(truth)


@FAST
@given(box, box, st.floats(-1e3, 1e3, **finite), st.floats(-1e3, 1e3, **finite), yaws)
def test_sat_translation_and_rotation_invariant(b1, b2, tx, ty, rot):
    assume(_clear(b1, b2, 1e-3))
    base = bool(boxes_overlap(*b1, *b2))

    def moved(b):
        x, y, yaw, ln, wd = b
        c, s = math.cos(rot), math.sin(rot)
        return (c * x - s * y + tx, s * x + c * y + ty, float(wrap_angle(yaw + rot)), ln, wd)

    assert bool(boxes_overlap(*moved(b1), *moved(b2))) == base
