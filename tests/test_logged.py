"""Logged-data loaders (generic CSV, highD) on the fixtures of ``tests/fixtures`` and on bad inputs."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from r1sim_sumo.data.logged import (
    HIGHD_DEFAULT_SPEED_LIMIT_MPS,
    LoggedDataError,
    load_generic_csv,
    load_highd,
    resample_track_10hz,
)
from r1sim_sumo.scenario import CURRENT_INDEX, LANE_CENTRE, N_WINDOW_10HZ, ROAD_EDGE, ScenarioError

FIX = Path(__file__).resolve().parent / "fixtures"
HIGHD = FIX / "highd"
GEN_TRACKS, GEN_MAP = FIX / "generic_csv" / "tracks.csv", FIX / "generic_csv" / "map.csv"
UPPER, LOWER = [8.50, 12.30, 16.10], [20.60, 24.40, 28.20]  # as in make_fixtures.py (image y)


@pytest.fixture
def highd_copy(tmp_path):
    d = tmp_path / "highd"
    shutil.copytree(HIGHD, d)
    return d


@pytest.fixture
def generic_copy(tmp_path):
    shutil.copy(GEN_TRACKS, tmp_path / "tracks.csv")
    shutil.copy(GEN_MAP, tmp_path / "map.csv")
    return tmp_path / "tracks.csv", tmp_path / "map.csv"


# ---------------------------------------------------------------------------- highD


def test_highd_windows_shapes_and_metadata():
    scs = load_highd(HIGHD, 1)
    assert len(scs) == 2  # 12 s at 10 Hz = 120 steps -> windows at 0 and 20
    for sc in scs:
        assert sc.num_steps == N_WINDOW_10HZ and sc.current_index == CURRENT_INDEX
        assert sc.metadata["source"] == "highd" and sc.metadata["recording_id"] == 1
        assert sc.metadata["speed_limit_mps"] == pytest.approx(33.33)
        assert sc.agents.valid[:, CURRENT_INDEX].all()
    assert scs[0].agents.ids.tolist() == ["1", "2", "3", "4", "5"]  # vehicle 6 enters at t = 2.44 s (step 24)
    assert "6" in scs[1].agents.ids.tolist()
    assert scs[1].metadata["start_time_s"] == pytest.approx(2.04)
    assert len(load_highd(HIGHD, 1, stride_steps=5, max_windows=3)) == 3


def test_highd_frame_flip_centre_and_yaw():
    tracks = pd.read_csv(HIGHD / "01_tracks.csv")
    sc = load_highd(HIGHD, 1)[0]
    a = sc.agents
    # grid step k is t = 0.04 + 0.1 k s = frame 1 + 2.5 k; step 10 = frame 26 exactly
    for vid in (1, 2, 4):
        r = tracks[(tracks.id == vid) & (tracks.frame == 26)].iloc[0]
        i = a.ids.tolist().index(str(vid))
        assert a.x_m[i, 10] == pytest.approx(r.x + r.width / 2, abs=1e-4)
        assert a.y_m[i, 10] == pytest.approx(-(r.y + r.height / 2), abs=1e-4)  # y down -> y up
        assert a.length_m[i] == pytest.approx(r.width) and a.width_m[i] == pytest.approx(r.height)
        assert a.speed_mps[i, 10] == pytest.approx(abs(r.xVelocity), abs=1e-4)
    i4 = a.ids.tolist().index("4")  # drivingDirection 1: towards -x
    assert abs(abs(a.yaw_rad[i4, 10]) - math.pi) < 1e-6
    assert a.vx_mps[i4, 10] < 0
    i1 = a.ids.tolist().index("1")
    assert abs(a.yaw_rad[i1, 10]) < 1e-6
    # the truck is 16 m long
    assert a.length_m[a.ids.tolist().index("2")] == pytest.approx(16.0)


def test_highd_lane_change_yaw_sign():
    # vehicle 3 moves from lower lane 0 to lane 1 (+y in the image = towards -y internally) while driving +x
    sc = load_highd(HIGHD, 1)[0]
    i = sc.agents.ids.tolist().index("3")
    t6 = round((6.0 - 0.04) / 0.1)  # mid lane change
    assert sc.agents.yaw_rad[i, t6] < -0.02
    assert sc.agents.vy_mps[i, t6] < 0
    dy = np.diff(sc.agents.y_m[i, 40:80])
    assert (dy <= 1e-4).all() and dy.sum() < -3.0
    # yaw agrees with the direction of motion computed from positions
    mv = np.arctan2(np.diff(sc.agents.y_m[i]), np.diff(sc.agents.x_m[i]))
    assert np.abs(mv - sc.agents.yaw_rad[i, :-1]).max() < 0.02


def test_highd_map_lanes_between_markings():
    sc = load_highd(HIGHD, 1)[0]
    m = sc.map
    lanes = {m.lane_id[i]: m.polyline(i) for i in range(m.num_polylines) if m.kind[i] == LANE_CENTRE}
    edges = {m.lane_id[i]: m.polyline(i) for i in range(m.num_polylines) if m.kind[i] == ROAD_EDGE}
    assert set(lanes) == {"upper_0", "upper_1", "lower_0", "lower_1"}
    assert set(edges) == {"upper#left", "upper#right", "lower#left", "lower#right"}
    for name, marks in (("upper", UPPER), ("lower", LOWER)):
        for k in range(2):
            p = lanes[f"{name}_{k}"]
            np.testing.assert_allclose(p[:, 1], -0.5 * (marks[k] + marks[k + 1]), atol=1e-5)
            d = p[-1, 0] - p[0, 0]
            assert (d < 0) if name == "upper" else (d > 0)  # upper drives -x, lower +x
            assert m.width_m[m.lane_id.tolist().index(f"{name}_{k}")] == pytest.approx(marks[k + 1] - marks[k], abs=1e-5)
    # road edges at the outermost markings; "left" is the median side for both carriageways
    assert edges["upper#right"][0, 1] == pytest.approx(-UPPER[0]) and edges["upper#left"][0, 1] == pytest.approx(-UPPER[-1])
    assert edges["lower#left"][0, 1] == pytest.approx(-LOWER[0]) and edges["lower#right"][0, 1] == pytest.approx(-LOWER[-1])
    # every vehicle lies on the road between the outermost edges
    a = sc.agents
    assert (a.y_m[a.valid] < -UPPER[0]).all() and (a.y_m[a.valid] > -LOWER[-1]).all()
    x0, _, x1, _ = m.bounds()
    assert x0 <= a.x_m[a.valid].min() and x1 >= a.x_m[a.valid].max()


def test_highd_no_speed_limit_uses_default(highd_copy):
    p = highd_copy / "01_recordingMeta.csv"
    df = pd.read_csv(p)
    df["speedLimit"] = -1.0
    df.to_csv(p, index=False)
    sc = load_highd(highd_copy, 1)[0]
    assert sc.metadata["speed_limit_mps"] == pytest.approx(HIGHD_DEFAULT_SPEED_LIMIT_MPS)
    assert not sc.metadata["speed_limit_given"]
    assert np.allclose(sc.map.speed_limit_mps[sc.map.kind == LANE_CENTRE], HIGHD_DEFAULT_SPEED_LIMIT_MPS)


def test_highd_missing_file(highd_copy):
    (highd_copy / "01_tracksMeta.csv").unlink()
    with pytest.raises(LoggedDataError, match="01_tracksMeta.csv"):
        load_highd(highd_copy, 1)
    with pytest.raises(LoggedDataError, match="07_tracks.csv"):
        load_highd(highd_copy, 7)


def test_highd_missing_column_names_it(highd_copy):
    p = highd_copy / "01_tracks.csv"
    pd.read_csv(p).drop(columns=["yVelocity"]).to_csv(p, index=False)
    with pytest.raises(LoggedDataError, match=r"01_tracks\.csv.*yVelocity"):
        load_highd(highd_copy, 1)


def test_highd_kmh_speeds_refused(highd_copy):
    p = highd_copy / "01_tracks.csv"
    df = pd.read_csv(p)
    df["xVelocity"] *= 3.6  # slowest vehicle: 17 m/s -> 61 "m/s", still below the 80 m/s bound
    df["yVelocity"] *= 3.6
    df = df[df.id.isin([5])]
    df.to_csv(p, index=False)
    with pytest.raises(LoggedDataError, match="km/h"):
        load_highd(highd_copy, 1)


def test_highd_nan_refused_names_row_and_column(highd_copy):
    p = highd_copy / "01_tracks.csv"
    df = pd.read_csv(p)
    df.loc[41, "x"] = np.nan
    df.to_csv(p, index=False)
    with pytest.raises(LoggedDataError, match=r"01_tracks\.csv: row 43 .*column 'x'"):
        load_highd(highd_copy, 1)


def test_highd_empty_and_unknown_track(highd_copy):
    p = highd_copy / "01_tracksMeta.csv"
    df = pd.read_csv(p)
    df[df.id != 3].to_csv(p, index=False)
    with pytest.raises(LoggedDataError, match=r"track 3 not listed"):
        load_highd(highd_copy, 1)
    p.write_text("")
    with pytest.raises(LoggedDataError, match=r"01_tracksMeta\.csv: file is empty"):
        load_highd(highd_copy, 1)
    p.write_text(",".join(df.columns) + "\n")
    with pytest.raises(LoggedDataError, match="no data rows"):
        load_highd(highd_copy, 1)


# ---------------------------------------------------------------------------- generic CSV


def test_generic_csv_fixture():
    scs = load_generic_csv(GEN_TRACKS, GEN_MAP)
    assert len(scs) == 2  # scene_a: 12 s -> 121 steps -> windows at 0, 20; scene_b (6 s) is too short
    sc = scs[0]
    assert sc.metadata["source"] == "csv" and sc.metadata["scene_id"] == "scene_a"
    assert sc.agents.ids.tolist() == ["car_a", "car_b", "bike_1", "ped_1"]
    assert sc.agents.agent_type.tolist() == [0, 0, 1, 2]
    # vx/vy derived from speed and yaw when absent
    i = 3  # pedestrian walking north at 1.4 m/s
    assert sc.agents.vx_mps[i, 10] == pytest.approx(0.0, abs=1e-3) and sc.agents.vy_mps[i, 10] == pytest.approx(1.4, abs=1e-3)
    assert sc.map.num_polylines == 4 and sorted(sc.map.kind.tolist()) == [0, 0, 1, 1]
    assert sc.map.speed_limit_mps[0] == pytest.approx(13.89)
    assert scs[1].metadata["start_time_s"] == pytest.approx(2.0)


def _write_constant_velocity(path: Path, hz: float, duration_s: float, yaw: float, speed: float, t0: float = 0.3):
    rows = []
    n = int(duration_s * hz) + 1
    for k in range(n):
        t = t0 + k / hz
        rows.append(dict(scene_id="cv", frame=k, time_s=t, agent_id="a", agent_type="vehicle",
                         x_m=5 + speed * math.cos(yaw) * (t - t0), y_m=-2 + speed * math.sin(yaw) * (t - t0),
                         yaw_rad=yaw, speed_mps=speed, length_m=4.5, width_m=1.9))
    pd.DataFrame(rows).to_csv(path, index=False)


@pytest.mark.parametrize("hz", [7.0, 25.0, 30.0])
def test_resampling_constant_velocity_exact(tmp_path, hz):
    yaw, speed = 2.5, 9.0
    _write_constant_velocity(tmp_path / "t.csv", hz, 11.0, yaw, speed)
    shutil.copy(GEN_MAP, tmp_path / "map.csv")
    sc = load_generic_csv(tmp_path / "t.csv", tmp_path / "map.csv", stride_steps=10)[0]
    a = sc.agents
    assert a.valid.all()
    t = sc.metadata["start_time_s"] - 0.3 + 0.1 * np.arange(N_WINDOW_10HZ)  # time since the first sample
    np.testing.assert_allclose(a.x_m[0], 5 + speed * math.cos(yaw) * t, atol=1e-4)
    np.testing.assert_allclose(a.y_m[0], -2 + speed * math.sin(yaw) * t, atol=1e-4)
    np.testing.assert_allclose(np.hypot(np.diff(a.x_m[0]), np.diff(a.y_m[0])), speed * 0.1, atol=1e-4)
    np.testing.assert_allclose(a.yaw_rad[0], yaw, atol=1e-6)
    np.testing.assert_allclose(a.vx_mps[0], speed * math.cos(yaw), atol=1e-4)


def test_resample_unwraps_angles_and_marks_gaps():
    t = np.array([0.0, 0.2, 0.4, 1.4, 1.6])  # a 1 s gap between 0.4 and 1.4
    yaw = np.array([3.0, -3.0, 3.0, 3.1, 3.1])  # crosses +-pi: must interpolate the short way
    k0, out, valid = resample_track_10hz(t, 0.0, {"yaw_rad": yaw, "x_m": t * 10})
    assert k0 == 0 and len(valid) == 17
    assert abs(abs(out["yaw_rad"][1]) - math.pi) < 0.2  # halfway between 3.0 and -3.0 is pi, not 0
    assert valid[:5].all() and not valid[5:14].any() and valid[14:].all()
    np.testing.assert_allclose(out["x_m"][valid], 10 * 0.1 * np.flatnonzero(valid), atol=1e-9)


def test_generic_missing_column_names_file_and_column(generic_copy):
    tracks, map_ = generic_copy
    pd.read_csv(tracks).drop(columns=["speed_mps"]).to_csv(tracks, index=False)
    with pytest.raises(LoggedDataError, match=r"tracks\.csv.*speed_mps"):
        load_generic_csv(tracks, map_)
    pd.read_csv(map_).drop(columns=["kind"]).to_csv(map_, index=False)
    with pytest.raises(LoggedDataError, match=r"map\.csv.*kind"):
        load_generic_csv(tracks, map_)


def test_generic_nan_row_refused(generic_copy):
    tracks, map_ = generic_copy
    df = pd.read_csv(tracks)
    df.loc[10, "yaw_rad"] = np.nan
    df.to_csv(tracks, index=False)
    with pytest.raises(LoggedDataError, match=r"tracks\.csv: row 12 .*column 'yaw_rad'"):
        load_generic_csv(tracks, map_)


def test_generic_kmh_refused(generic_copy):
    tracks, map_ = generic_copy
    df = pd.read_csv(tracks)
    df["speed_mps"] *= 3.6
    df.to_csv(tracks, index=False)
    with pytest.raises(LoggedDataError, match="km/h"):
        load_generic_csv(tracks, map_)
    df["speed_mps"] = 120.0
    df.to_csv(tracks, index=False)
    with pytest.raises(LoggedDataError, match=r"speed_mps.*km/h"):
        load_generic_csv(tracks, map_)


def test_generic_bad_values_refused(generic_copy):
    tracks, map_ = generic_copy
    base = pd.read_csv(tracks)
    cases = [
        ("yaw_rad", 90.0, "degrees"),
        ("agent_type", "truck", "agent_type"),
        ("width_m", 0.0, "width_m"),
        ("x_m", "abc", "not a number"),
    ]
    for col, value, pattern in cases:
        df = base.copy()
        df[col] = df[col].astype(object)
        df.loc[5, col] = value
        df.to_csv(tracks, index=False)
        with pytest.raises(LoggedDataError, match=pattern) as exc:
            load_generic_csv(tracks, map_)
        assert "row 7" in str(exc.value) and col in str(exc.value)
    dup = pd.concat([base, base.iloc[[3]]])
    dup.to_csv(tracks, index=False)
    with pytest.raises(LoggedDataError, match="two rows at time"):
        load_generic_csv(tracks, map_)


def test_generic_empty_and_missing_files(generic_copy, tmp_path):
    tracks, map_ = generic_copy
    with pytest.raises(LoggedDataError, match="nope.csv: file not found"):
        load_generic_csv(tmp_path / "nope.csv", map_)
    tracks.write_text("")
    with pytest.raises(LoggedDataError, match="empty"):
        load_generic_csv(tracks, map_)
    map_.write_text("polyline_id,kind,x_m,y_m,speed_limit_mps,width_m\n")
    with pytest.raises(LoggedDataError, match="no data rows"):
        load_generic_csv(tracks, map_)
    assert issubclass(LoggedDataError, ScenarioError)


def test_generic_vx_without_vy_refused(generic_copy):
    tracks, map_ = generic_copy
    df = pd.read_csv(tracks)
    df["vx_mps"] = df["speed_mps"]
    df.to_csv(tracks, index=False)
    with pytest.raises(LoggedDataError, match="vy_mps"):
        load_generic_csv(tracks, map_)
