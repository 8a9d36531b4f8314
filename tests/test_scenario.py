"""Scenario format: save/load round trips, shards sharing maps, datasets, validate() and corrupted files."""

from __future__ import annotations

import json
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from r1sim_sumo.scenario import (
    CURRENT_INDEX,
    N_WINDOW_10HZ,
    AgentTracks,
    MapPolylines,
    Scenario,
    ScenarioDataset,
    ScenarioError,
    read_shard,
    shard_size,
    write_dataset,
    write_shard,
)


def make_map(num_steps: int = N_WINDOW_10HZ, with_tl: bool = False, y_shift: float = 0.0) -> MapPolylines:
    xs = np.linspace(0, 100, 11)
    lanes = [np.stack([xs, np.full_like(xs, y + y_shift)], 1) for y in (-1.75, 1.75)]
    edges = [np.stack([xs, np.full_like(xs, y + y_shift)], 1) for y in (-3.5, 3.5)]
    tl = None
    if with_tl:
        tl = np.zeros((4, num_steps), np.int8)
        tl[0, :30], tl[0, 30:40], tl[0, 40:] = 1, 2, 3
    return MapPolylines.from_lists(
        lanes + edges, [0, 0, 1, 1], ["l0", "l1", "e#right", "e#left"], [13.9, 13.9, 0, 0], [3.5, 3.5, 0, 0],
        tl_state=tl, successors=[(0, 1)],
    )


def make_scenario(num_agents: int = 3, num_steps: int = N_WINDOW_10HZ, seed: int = 0, **map_kw) -> Scenario:
    rng = np.random.default_rng(seed)
    a = AgentTracks.empty(num_agents, num_steps)
    a.ids = np.array([f"veh_{i}" for i in range(num_agents)])
    t = np.arange(num_steps) * 0.1
    v = rng.uniform(5, 15, num_agents)
    a.x_m[:] = rng.uniform(0, 30, (num_agents, 1)) + v[:, None] * t
    a.y_m[:] = rng.choice([-1.75, 1.75], (num_agents, 1))
    a.speed_mps[:] = v[:, None]
    a.vx_mps[:] = v[:, None]
    a.valid[:] = True
    a.valid[-1, :5] = False  # last agent appears at step 5
    a.x_m[-1, :5] = 0.0
    return Scenario(agents=a, map=make_map(num_steps, **map_kw), metadata={"source": "test", "network": "straight", "seed": seed})


def assert_same(a: Scenario, b: Scenario) -> None:
    for f in AgentTracks.FIELDS:
        x, y = getattr(a.agents, f), getattr(b.agents, f)
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=f"agents.{f}")
    for f in MapPolylines.FIELDS:
        np.testing.assert_array_equal(getattr(a.map, f), getattr(b.map, f), err_msg=f"map.{f}")
    assert {k: v for k, v in a.metadata.items() if k != "_path"} == b.metadata
    assert a.current_index == b.current_index and a.dt_s == b.dt_s


# ---------------------------------------------------------------------------- round trips


def test_save_load_round_trip(tmp_path):
    sc = make_scenario(with_tl=True)
    path = sc.save(tmp_path / "one")
    assert path.suffix == ".npz" and path.exists()
    back = Scenario.load(path)
    assert_same(sc.validate(), back)
    assert back.agents.x_m.dtype == np.float32 and back.agents.valid.dtype == bool
    assert back.map.tl_state.shape == (4, N_WINDOW_10HZ)


def test_shard_with_shared_map_stores_it_once(tmp_path):
    # same static map, different traffic-light states per scenario, plus one other map
    s0 = make_scenario(seed=0, with_tl=True)
    s1 = make_scenario(seed=1, with_tl=True)
    s1.map = s1.map.with_tl_state(np.full_like(s1.map.tl_state, 3))
    s2 = make_scenario(seed=2, y_shift=10.0)
    s2.agents.y_m += 10.0
    path = write_shard(tmp_path / "shard.npz", [s0, s1, s2])
    with zipfile.ZipFile(path) as z:
        map_keys = {n.split("/")[1] for n in z.namelist() if n.startswith("map/")}
    assert len(map_keys) == 2
    assert shard_size(path) == 3
    back = read_shard(path)
    for a, b in zip((s0, s1, s2), back, strict=True):
        assert_same(a, b)
    assert (back[1].map.tl_state == 3).all() and back[0].map.tl_state[0, 35] == 2
    only = read_shard(path, indices=[2])
    assert len(only) == 1 and np.allclose(only[0].map.points_m[:, 1].min(), 6.5)


def test_dataset_folder_with_manifest(tmp_path):
    scs = [make_scenario(seed=i) for i in range(7)]
    root = write_dataset(tmp_path / "ds", scs, shard_size=3, extra_manifest={"network": "straight"})
    manifest = json.loads((root / "manifest.json").read_text())
    assert [s["num_scenarios"] for s in manifest["shards"]] == [3, 3, 1]
    assert manifest["num_scenarios"] == 7 and manifest["network"] == "straight"
    ds = ScenarioDataset(root, cache_shards=1)
    assert len(ds) == 7
    assert_same(scs[4], ds[4])
    assert_same(scs[6], ds[-1])
    assert [sc.metadata["seed"] for sc in ds] == list(range(7))
    with pytest.raises(IndexError):
        ds[7]
    with pytest.raises(FileExistsError):
        write_dataset(root, scs)


def test_missing_shard_listed_in_manifest(tmp_path):
    root = write_dataset(tmp_path / "ds", [make_scenario(seed=i) for i in range(4)], shard_size=2)
    (root / "shard-00001.npz").unlink()
    with pytest.raises(ScenarioError, match="shard-00001.npz"):
        ScenarioDataset(root)


def test_missing_or_broken_manifest(tmp_path):
    with pytest.raises(ScenarioError, match="manifest.json"):
        ScenarioDataset(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(ScenarioError, match="manifest.json"):
        ScenarioDataset(tmp_path)


# ---------------------------------------------------------------------------- corrupted files


def test_truncated_npz_names_file(tmp_path):
    path = make_scenario().save(tmp_path / "trunc.npz")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ScenarioError, match="trunc.npz"):
        read_shard(path)


def test_garbage_file_names_file(tmp_path):
    path = tmp_path / "garbage.npz"
    path.write_bytes(b"this is not a zip archive" * 10)
    with pytest.raises(ScenarioError, match="garbage.npz"):
        read_shard(path)
    with pytest.raises(ScenarioError, match="garbage.npz"):
        shard_size(path)


def test_corrupted_member_bytes_names_file(tmp_path):
    # flip bytes inside the compressed data of the agents' x_m member (the zip directory stays intact)
    path = make_scenario().save(tmp_path / "flipped.npz")
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("s0/agents/x_m.npy")
    raw = bytearray(path.read_bytes())
    start = info.header_offset + 30 + len(info.filename) + len(info.extra) + 8
    for k in range(start, start + 24):
        raw[k] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(ScenarioError, match="flipped.npz"):
        read_shard(path)


def test_missing_file_and_missing_field(tmp_path):
    with pytest.raises(ScenarioError, match="nothere.npz"):
        read_shard(tmp_path / "nothere.npz")
    path = make_scenario().save(tmp_path / "ok.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k != "s0/agents/yaw_rad"}
    np.savez_compressed(tmp_path / "nofield.npz", **arrays)
    with pytest.raises(ScenarioError, match="yaw_rad"):
        read_shard(tmp_path / "nofield.npz")


# ---------------------------------------------------------------------------- validate() rejections


def _mutated(fn) -> Scenario:
    sc = make_scenario()
    fn(sc)
    return sc


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda s: s.agents.x_m.__setitem__((0, 3), np.nan), "agents.x_m"),
        (lambda s: s.agents.speed_mps.__setitem__((1, 50), np.inf), "agents.speed_mps"),
        (lambda s: setattr(s.agents, "y_m", s.agents.y_m[:, :-1]), "agents.y_m"),
        (lambda s: setattr(s.agents, "length_m", s.agents.length_m[:2]), "agents.length_m"),
        (lambda s: setattr(s.agents, "yaw_rad", np.full_like(s.agents.yaw_rad, 90.0)), "agents.yaw_rad"),
        (lambda s: setattr(s.agents, "speed_mps", s.agents.speed_mps * 3.6 * 3), "agents.speed_mps"),
        (lambda s: s.agents.ids.__setitem__(1, "veh_0"), "agents.ids"),
        (lambda s: s.agents.agent_type.__setitem__(0, 7), "agents.agent_type"),
        (lambda s: s.agents.width_m.__setitem__(0, 0.0), "width_m"),
        (lambda s: s.agents.valid.__setitem__(0, False), "agents.valid"),
        (lambda s: setattr(s, "map", MapPolylines.from_lists([], [], [], [], [])), "map"),
        (lambda s: setattr(s, "map", s.map.with_tl_state(np.zeros((4, 7), np.int8))), "map.tl_state"),
        (lambda s: setattr(s.map, "kind", np.array([0, 0, 1, 5], np.int8)), "map.kind"),
        (lambda s: setattr(s.map, "successors", np.array([[0, 9]], np.int32)), "map.successors"),
        (lambda s: setattr(s, "current_index", 200), "current_index"),
    ],
    ids=["nan", "inf", "shape_T", "shape_A", "yaw_degrees", "kmh", "dup_ids", "bad_type", "zero_width",
         "never_valid", "empty_map", "tl_shape", "bad_kind", "bad_successor", "current_index"],
)
def test_validate_rejects_and_names_field(mutate, field):
    sc = _mutated(mutate)
    with pytest.raises(ScenarioError) as exc:
        sc.validate(source="somefile.npz")
    msg = str(exc.value)
    assert field in msg, msg
    assert "somefile.npz" in msg


def test_validate_rejects_zero_agents():
    sc = make_scenario()
    sc.agents = AgentTracks.empty(0, N_WINDOW_10HZ)
    with pytest.raises(ScenarioError, match="zero agents"):
        sc.validate()


def test_validate_ignores_garbage_at_invalid_steps():
    sc = make_scenario()
    sc.agents.x_m[-1, 0] = np.nan  # the last agent is invalid at steps 0..4
    sc.agents.yaw_rad[-1, 1] = 400.0
    assert sc.validate() is sc


def test_write_shard_refuses_invalid(tmp_path):
    sc = make_scenario()
    sc.agents.x_m[0, 0] = np.nan
    with pytest.raises(ScenarioError, match=r"bad\.npz.*agents\.x_m"):
        write_shard(tmp_path / "bad.npz", [sc])
    assert not (tmp_path / "bad.npz").exists()


# ---------------------------------------------------------------------------- property test


@st.composite
def scenarios(draw) -> Scenario:
    A = draw(st.integers(1, 5))
    T = draw(st.integers(CURRENT_INDEX + 1, 20))

    def arr(lo, hi, shape):
        el = st.floats(float(np.float32(lo)), float(np.float32(hi)), allow_nan=False, width=32)
        return draw(hnp.arrays(np.float32, shape, elements=el))

    valid = draw(hnp.arrays(bool, (A, T)))
    valid[np.arange(A), draw(hnp.arrays(np.int64, (A,), elements=st.integers(0, T - 1)))] = True
    ids = draw(st.lists(st.text(alphabet="abcxyz_0123é", min_size=1, max_size=8), min_size=A, max_size=A, unique=True))
    a = AgentTracks(
        ids=np.array(ids), agent_type=draw(hnp.arrays(np.int8, (A,), elements=st.integers(0, 2))),
        length_m=arr(0.1, 20, (A,)), width_m=arr(0.1, 5, (A,)), x_m=arr(-1e4, 1e4, (A, T)), y_m=arr(-1e4, 1e4, (A, T)),
        yaw_rad=arr(-3.14159, 3.14159, (A, T)), speed_mps=arr(-79, 79, (A, T)), vx_mps=arr(-79, 79, (A, T)),
        vy_mps=arr(-79, 79, (A, T)), valid=valid,
    )
    L = draw(st.integers(1, 4))
    polys = [arr(-1e3, 1e3, (draw(st.integers(2, 6)), 2)) for _ in range(L)]
    tl = draw(hnp.arrays(np.int8, (L, T), elements=st.integers(0, 3))) if draw(st.booleans()) else None
    m = MapPolylines.from_lists(
        polys, draw(st.lists(st.integers(0, 1), min_size=L, max_size=L)), [f"lane{i}" for i in range(L)],
        arr(0, 40, (L,)), arr(0, 5, (L,)), tl_state=tl,
    )
    meta = {"source": draw(st.sampled_from(["sumo", "csv", "highd"])), "seed": draw(st.integers(0, 2**31)),
            "note": draw(st.text(max_size=10))}
    return Scenario(agents=a, map=m, metadata=meta, current_index=draw(st.integers(0, T - 1)))


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(st.lists(scenarios(), min_size=1, max_size=3))
def test_save_load_identity_property(scs):
    with tempfile.TemporaryDirectory() as d:
        path = write_shard(Path(d) / "p.npz", scs)
        back = read_shard(path)
    assert len(back) == len(scs)
    for a, b in zip(scs, back, strict=True):
        assert_same(a, b)


def test_map_select_keeps_chosen_polylines_and_their_successors():
    m = make_map(with_tl=True)
    lanes = m.select(m.kind == 0)  # the two lane centres, which are successors of each other
    assert lanes.num_polylines == 2 and list(lanes.lane_id) == ["l0", "l1"]
    np.testing.assert_array_equal(lanes.polyline(1), m.polyline(1))
    np.testing.assert_array_equal(lanes.successors, [[0, 1]])
    assert lanes.tl_state.shape == (2, m.tl_state.shape[1])
    reordered = m.select(np.array([3, 1]))  # an edge and the successor lane of a dropped one: no pair left
    assert list(reordered.lane_id) == ["e#left", "l1"] and len(reordered.successors) == 0
    np.testing.assert_allclose(reordered.speed_limit_mps, [0.0, 13.9], rtol=1e-6)
    np.testing.assert_array_equal(reordered.polyline(0), m.polyline(3))
