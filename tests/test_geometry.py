"""Frames, angle conventions, box corners and the batched SAT overlap (checked against shapely)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
import torch
from hypothesis import given, settings
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

torch.set_num_threads(1)

finite = dict(allow_nan=False, allow_infinity=False)
yaws = st.floats(-20.0, 20.0, **finite)


def _angle_diff(a, b):
    return np.abs(wrap_angle(np.asarray(a, np.float64) - np.asarray(b, np.float64)))


# ---------------------------------------------------------------------------- angles


@pytest.mark.parametrize(
    ("sumo_deg", "yaw"),
    [(0.0, math.pi / 2), (90.0, 0.0), (180.0, -math.pi / 2), (270.0, math.pi), (45.0, math.pi / 4)],
)
def test_sumo_angle_known_values(sumo_deg, yaw):
    # SUMO: 0 = north, clockwise; internal: 0 = east, counter-clockwise
    assert _angle_diff(sumo_angle_deg_to_yaw_rad(sumo_deg), yaw) < 1e-12
    assert abs(((yaw_rad_to_sumo_angle_deg(yaw) - sumo_deg) + 180) % 360 - 180) < 1e-9


@given(yaws)
def test_yaw_sumo_round_trip(yaw):
    back = sumo_angle_deg_to_yaw_rad(yaw_rad_to_sumo_angle_deg(yaw))
    assert _angle_diff(back, yaw) < 1e-9
    assert -math.pi <= back < math.pi + 1e-12


@given(st.floats(0.0, 360.0, exclude_max=True, **finite))
def test_sumo_yaw_round_trip(deg):
    back = yaw_rad_to_sumo_angle_deg(sumo_angle_deg_to_yaw_rad(deg))
    assert 0.0 <= back < 360.0
    assert abs(((back - deg) + 180) % 360 - 180) < 1e-9


@given(yaws)
def test_wrap_angle_range_and_identity(a):
    w = wrap_angle(a)
    assert -math.pi <= w < math.pi
    assert abs(math.remainder(w - a, 2 * math.pi)) < 1e-9


def test_wrap_angle_torch_and_numpy_agree():
    a = np.linspace(-10, 10, 101)
    np.testing.assert_allclose(wrap_angle(torch.from_numpy(a)).numpy(), wrap_angle(a), atol=1e-12)


# ---------------------------------------------------------------------------- reference points


def test_front_bumper_centre_known():
    # heading north: the front bumper is length/2 north of the centre
    fx, fy = centre_to_front_bumper(10.0, 20.0, math.pi / 2, 4.0)
    assert fx == pytest.approx(10.0, abs=1e-12) and fy == pytest.approx(22.0)
    # SUMO angle 90 (east): centre is length/2 west of the bumper
    cx, cy = front_bumper_to_centre(0.0, 0.0, sumo_angle_deg_to_yaw_rad(90.0), 5.0)
    assert cx == pytest.approx(-2.5) and cy == pytest.approx(0.0, abs=1e-12)


@given(st.floats(-1e3, 1e3, **finite), st.floats(-1e3, 1e3, **finite), yaws, st.floats(0.1, 20.0, **finite))
def test_front_bumper_round_trip(x, y, yaw, length):
    fx, fy = centre_to_front_bumper(x, y, yaw, length)
    assert math.hypot(fx - x, fy - y) == pytest.approx(length / 2, rel=1e-9, abs=1e-9)
    bx, by = front_bumper_to_centre(fx, fy, yaw, length)
    assert bx == pytest.approx(x, abs=1e-9) and by == pytest.approx(y, abs=1e-9)


# ---------------------------------------------------------------------------- highway-env frame


def test_highway_frame_flip_known():
    # highway-env: moving "down" the screen (+y_hw, heading +pi/2) is moving south internally (yaw -pi/2)
    x, y, yaw = highway_to_internal(3.0, 4.0, math.pi / 2)
    assert x == 3.0 and float(y) == -4.0 and _angle_diff(yaw, -math.pi / 2) < 1e-12


@given(st.floats(-1e3, 1e3, **finite), st.floats(-1e3, 1e3, **finite), yaws)
def test_highway_frame_round_trip(x, y, h):
    xi, yi, yawi = highway_to_internal(x, y, h)
    xh, yh, hh = internal_to_highway(xi, yi, yawi)
    assert xh == x and float(yh) == y and _angle_diff(hh, h) < 1e-9
    # the velocity direction flips with the frame: (cos h, sin h) -> (cos yaw, sin yaw) = (cos h, -sin h)
    assert math.cos(yawi) == pytest.approx(math.cos(h), abs=1e-9)
    assert math.sin(yawi) == pytest.approx(-math.sin(h), abs=1e-9)


# ---------------------------------------------------------------------------- box corners


def test_box_corners_axis_aligned_order():
    c = box_corners(np.array(1.0), np.array(2.0), np.array(0.0), 4.0, 2.0)
    # front-left, rear-left, rear-right, front-right
    np.testing.assert_allclose(c, [[3, 3], [-1, 3], [-1, 1], [3, 1]], atol=1e-12)


def test_box_corners_rotated_and_batched_numpy_torch():
    rng = np.random.default_rng(0)
    x, y, yaw = rng.normal(size=(3, 3, 5)) * np.array([10.0, 10.0, 3.0])[:, None, None]  # [3, 5] each
    length, width = rng.uniform(1, 6, size=(2, 3, 5))
    c = box_corners(x, y, yaw, length, width)  # [3, 5, 4, 2]
    assert c.shape == (3, 5, 4, 2)
    np.testing.assert_allclose(c.mean(axis=-2), np.stack([x, y], -1), atol=1e-12)
    side_front = np.linalg.norm(c[..., 0, :] - c[..., 3, :], axis=-1)
    side_long = np.linalg.norm(c[..., 0, :] - c[..., 1, :], axis=-1)
    np.testing.assert_allclose(side_front, width, atol=1e-12)
    np.testing.assert_allclose(side_long, length, atol=1e-12)
    # the front edge lies ahead of the centre along the heading
    heading = np.stack([np.cos(yaw), np.sin(yaw)], -1)  # [3, 5, 2]
    ahead = ((c[..., 0, :] - np.stack([x, y], -1)) * heading).sum(-1)
    np.testing.assert_allclose(ahead, length / 2, atol=1e-12)
    tc = box_corners(*(torch.from_numpy(v) for v in (x, y, yaw, length, width)))
    np.testing.assert_allclose(tc.numpy(), c, atol=1e-12)


def test_box_corners_torch_scalar_size():
    x = torch.tensor([0.0, 10.0], dtype=torch.float64)
    c = box_corners(x, x * 0, x * 0, 4.0, 2.0)  # sizes as python floats
    assert c.shape == (2, 4, 2)
    np.testing.assert_allclose(c[1].numpy(), [[12, 1], [8, 1], [8, -1], [12, -1]], atol=1e-12)


# ---------------------------------------------------------------------------- SAT overlap vs shapely


def _random_pairs(n, seed):
    rng = np.random.default_rng(seed)
    b1 = [rng.uniform(-4, 4, n), rng.uniform(-4, 4, n), rng.uniform(-4, 4, n), rng.uniform(0.3, 8, n), rng.uniform(0.3, 3, n)]
    b2 = [rng.uniform(-4, 4, n), rng.uniform(-4, 4, n), rng.uniform(-4, 4, n), rng.uniform(0.3, 8, n), rng.uniform(0.3, 3, n)]
    return b1, b2


def _shapely_truth(b1, b2):
    p1 = shapely.polygons(box_corners(*b1))
    p2 = shapely.polygons(box_corners(*b2))
    truth = shapely.intersects(p1, p2)
    # pairs within 1e-7 m of touching are ambiguous in floating point: excluded from the comparison
    dist = shapely.distance(p1, p2)
    area = shapely.area(shapely.intersection(p1, p2))
    clear = (dist > 1e-7) | (area > 1e-7)
    return truth, clear


def test_boxes_overlap_matches_shapely_numpy_and_torch():
    b1, b2 = _random_pairs(4000, seed=1)
    truth, clear = _shapely_truth(b1, b2)
    assert clear.mean() > 0.99
    assert 0.2 < truth.mean() < 0.8  # both outcomes well represented
    got = boxes_overlap(*b1, *b2)
    assert got.dtype == bool and got.shape == (4000,)
    np.testing.assert_array_equal(got[clear], truth[clear])
    got_t = boxes_overlap(*(torch.from_numpy(v) for v in b1), *(torch.from_numpy(v) for v in b2))
    assert got_t.dtype == torch.bool
    np.testing.assert_array_equal(got_t.numpy()[clear], truth[clear])
    got_t32 = boxes_overlap(*(torch.from_numpy(v).float() for v in b1), *(torch.from_numpy(v).float() for v in b2))
    assert (got_t32.numpy()[clear] == truth[clear]).mean() > 0.999  # float32: only near-touching pairs may differ


def test_boxes_overlap_all_pairs_broadcast_matches_shapely():
    rng = np.random.default_rng(2)
    A = 40
    x, y = rng.uniform(-10, 10, (2, A))
    yaw = rng.uniform(-math.pi, math.pi, A)
    length, width = rng.uniform(1, 6, A), rng.uniform(0.5, 2.5, A)
    got = boxes_overlap(x[:, None], y[:, None], yaw[:, None], length[:, None], width[:, None],
                        x[None], y[None], yaw[None], length[None], width[None])  # [A, A]
    assert got.shape == (A, A)
    assert np.array_equal(got, got.T) and got.diagonal().all()
    polys = shapely.polygons(box_corners(x, y, yaw, length, width))
    truth = shapely.intersects(polys[:, None], polys[None])
    np.testing.assert_array_equal(got, truth)


def _corner_inside(c_a, c_b):
    """Any corner of box a strictly inside box b (shapely)."""
    poly = shapely.polygons(c_b)
    return bool(shapely.contains(poly, shapely.points(c_a)).any())


def test_plus_sign_overlap_without_corner_containment():
    # two long thin boxes crossing at their centres: no corner of either box is inside the other
    rng = np.random.default_rng(3)
    n = 500
    x, y = rng.uniform(-50, 50, (2, n))
    yaw = rng.uniform(-math.pi, math.pi, n)
    turn = yaw + math.pi / 2 + rng.uniform(-0.6, 0.6, n)
    length, width = rng.uniform(6, 12, n), rng.uniform(0.3, 1.0, n)
    shift = rng.uniform(-1, 1, (2, n))
    b1 = [x, y, yaw, length, width]
    b2 = [x + shift[0], y + shift[1], turn, length, width]
    c1, c2 = box_corners(*b1), box_corners(*b2)
    no_corner = np.array([not _corner_inside(c1[i], c2[i]) and not _corner_inside(c2[i], c1[i]) for i in range(n)])
    assert no_corner.mean() > 0.9  # the construction gives genuine "plus sign" crossings
    truth = shapely.intersects(shapely.polygons(c1), shapely.polygons(c2))
    assert truth[no_corner].all()
    assert boxes_overlap(*b1, *b2)[no_corner].all()
    t = boxes_overlap(*(torch.from_numpy(v) for v in b1), *(torch.from_numpy(v) for v in b2))
    assert t.numpy()[no_corner].all()


def test_separated_only_on_second_box_axis():
    # box 1 axis-aligned, box 2 rotated 45 deg near box 1's corner: box 1's axes see overlap,
    # only box 2's axes separate them (a test using only one box's axes would report a collision)
    b1 = (np.array(0.0), np.array(0.0), np.array(0.0), 2.0, 2.0)
    # box 2's axes are the diagonals: its side faces box 1's corner; touching at d = sqrt(2) + 0.5
    d = math.sqrt(2) + 0.5 + 0.05  # centre distance along the diagonal, just beyond touching
    b2 = (np.array(d / math.sqrt(2)), np.array(d / math.sqrt(2)), np.array(math.pi / 4), 1.0, 1.0)
    p1, p2 = shapely.polygons(box_corners(*b1)), shapely.polygons(box_corners(*b2))
    assert not shapely.intersects(p1, p2)
    assert not bool(boxes_overlap(*b1, *b2))
    dx = float(b2[0])
    assert abs(dx) < 1.0 + 0.5 * math.sqrt(2)  # projected on box 1's x axis they do overlap


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-5, 5, **finite), min_size=6, max_size=6), st.lists(st.floats(0.2, 6, **finite), min_size=4, max_size=4))
def test_boxes_overlap_symmetric_and_matches_shapely(p, s):
    b1 = (np.array(p[0]), np.array(p[1]), np.array(p[2]), s[0], s[1])
    b2 = (np.array(p[3]), np.array(p[4]), np.array(p[5]), s[2], s[3])
    truth, clear = _shapely_truth(b1, b2)
    got = bool(boxes_overlap(*b1, *b2))
    assert got == bool(boxes_overlap(*b2, *b1))
    if bool(clear):
        assert got == bool(truth)
