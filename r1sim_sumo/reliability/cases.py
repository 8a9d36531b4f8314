"""The hostile-input table: every bad input the project is checked against, defined once.

Each :class:`HostileCase` builds its input in a temporary folder, feeds it to the module that owns that input
(``scenario.py``, ``adapters/sumo_map.py``, ``data/logged.py``, ``config.py``, ``model/checkpoint.py``,
``commands/simulate.py``, ``safe_paths.py``...) and states the expected outcome:

* ``expect=<exception class>`` + ``match`` substrings: the input is refused with that error and the message
  names the file and the field (each substring must appear);
* ``expect=None`` + ``check``: a documented clean-up (e.g. a teleport jump split into a new agent); ``check``
  inspects the result and returns a one-line description (an ``AssertionError`` fails the case).

:func:`run_case` never raises: it returns a :class:`CaseOutcome` with ``passed`` and the message, so the
report can list failures too. ``tests/test_hostile_inputs.py`` asserts every case passes.
"""

from __future__ import annotations

import json
import logging
import math
import pickle
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from r1sim_sumo.reliability import fixtures as fx


@dataclass(frozen=True)
class HostileCase:
    name: str
    category: str
    description: str
    run: Callable[[Path], object]
    expect: type[BaseException] | None
    match: tuple[str, ...] = ()
    check: Callable[[object], str] | None = None
    marks: tuple[str, ...] = ()  # pytest marks the case needs ("sumo")


@dataclass
class CaseOutcome:
    name: str
    category: str
    description: str
    passed: bool
    outcome: str  # "refused" | "cleaned up" | "FAILED"
    message: str
    seconds: float = 0.0
    marks: tuple[str, ...] = field(default_factory=tuple)


def run_case(case: HostileCase, tmp: Path) -> CaseOutcome:
    """Run one case in folder ``tmp`` (created); never raises."""
    import time

    tmp.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    def out(passed: bool, outcome: str, message: str) -> CaseOutcome:
        return CaseOutcome(case.name, case.category, case.description, passed, outcome, message,
                           time.perf_counter() - t0, case.marks)

    try:
        result = case.run(tmp)
    except BaseException as exc:  # noqa: BLE001 - the whole point is to look at what came out
        if isinstance(exc, KeyboardInterrupt):
            raise
        msg = f"{type(exc).__name__}: {exc}"
        if case.expect is None:
            return out(False, "FAILED", f"expected a clean-up, got {msg}\n{traceback.format_exc(limit=3)}")
        if not isinstance(exc, case.expect):
            return out(False, "FAILED", f"expected {case.expect.__name__}, got {msg}\n{traceback.format_exc(limit=4)}")
        missing = [m for m in case.match if m not in str(exc)]
        if missing:
            return out(False, "FAILED", f"message lacks {missing}: {msg}")
        return out(True, "refused", msg)
    if case.expect is not None:
        return out(False, "FAILED", f"expected {case.expect.__name__}, but the input was accepted (result {type(result).__name__})")
    try:
        desc = case.check(result) if case.check else "accepted"
    except AssertionError as exc:
        return out(False, "FAILED", f"clean-up check failed: {exc}")
    return out(True, "cleaned up", desc)


# ---------------------------------------------------------------------------- helpers building inputs


def _bundled(kind: str) -> Path:
    from r1sim_sumo.resources import network_files

    f = network_files("motorway_merge")
    return f["net"] if kind == "net" else f["sumocfg"]


def _truncate_copy(src: Path, dst: Path, frac: float = 0.5) -> Path:
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * frac)])
    return dst


def _read_map(path: Path):
    from r1sim_sumo.adapters.sumo_map import read_sumo_map

    return read_sumo_map(path)


def _resolve_cfg(path: Path):
    from r1sim_sumo.commands.simulate import resolve_sumocfg

    return resolve_sumocfg(str(path), None)


def _sumocfg(tmp: Path, net: str, routes: str | None) -> Path:
    r = f'\n        <route-files value="{routes}"/>' if routes else ""
    p = tmp / "x.sumocfg"
    p.write_text(f'<configuration>\n    <input>\n        <net-file value="{net}"/>{r}\n    </input>\n</configuration>\n')
    return p


def _mutated(fn: Callable, n_agents: int = 4):
    def run(tmp: Path):
        sc = fx.toy_scenario(n_agents)
        fn(sc)
        return sc.validate(source=tmp / "scene.npz")
    return run


def _teleport(sc) -> None:
    sc.agents.x_m[1, 40:] += 500.0  # agent veh_1 jumps 500 m forward between steps 39 and 40


def _teleport_refused(tmp: Path):
    sc = fx.toy_scenario()
    _teleport(sc)
    return sc.validate(source=tmp / "scene.npz", check_jumps=True)


def _teleport_split(tmp: Path):
    from r1sim_sumo.scenario import split_teleports

    sc = fx.toy_scenario()
    _teleport(sc)
    return split_teleports(sc).validate(check_jumps=True)


def _check_split(sc) -> str:
    ids = sc.agents.ids.tolist()
    assert "veh_1~1" in ids and "veh_1" in ids, ids
    i, j = ids.index("veh_1"), ids.index("veh_1~1")
    assert not sc.agents.valid[i, 40:].any() and not sc.agents.valid[j, :40].any()
    return f"split into agents {ids[i]!r} (steps 0-39) and {ids[j]!r} (steps 40-90); validate(check_jumps=True) passes"


def _many_agents(tmp: Path):
    """2000 agents: validate, shard round trip and tokenization all succeed."""
    from r1sim_sumo.scenario import read_shard, write_shard
    from r1sim_sumo.tokens.batch import tokenize_scenario

    sc = fx.toy_scenario(2000)
    sc.agents.y_m[:] += np.repeat(np.arange(1000) * 0.0, 2)[:, None]
    back = read_shard(write_shard(tmp / "many.npz", [sc]))[0]
    scene = tokenize_scenario(back, fx.toy_vocab())
    return back, scene


def _check_many(res) -> str:
    sc, scene = res
    assert sc.agents.num_agents == 2000
    n = int(np.asarray(scene.agent_index).shape[0]) if hasattr(scene, "agent_index") else -1
    return f"2000 agents accepted: shard round trip + tokenization ({n} tokenized agents)"


def _zero_agents(tmp: Path):
    from r1sim_sumo.scenario import N_WINDOW_10HZ, AgentTracks

    sc = fx.toy_scenario()
    sc.agents = AgentTracks.empty(0, N_WINDOW_10HZ)
    return sc.validate(source=tmp / "scene.npz")


def _manifest(tmp: Path, file_name: str):
    from r1sim_sumo.scenario import ScenarioDataset

    root = fx.toy_dataset(tmp / "ds", n=2)
    m = json.loads((root / "manifest.json").read_text())
    m["shards"][0]["file"] = file_name
    (root / "manifest.json").write_text(json.dumps(m))
    return ScenarioDataset(root)


def _manifest_symlink_read(tmp: Path):
    """A shard behind a symlink (kept on another disk) is still read: only names are restricted on read."""
    from r1sim_sumo.scenario import ScenarioDataset

    root = fx.toy_dataset(tmp / "ds", n=2)
    elsewhere = tmp / "elsewhere"
    elsewhere.mkdir()
    shard = root / "shard-00000.npz"
    shard.rename(elsewhere / shard.name)
    shard.symlink_to(elsewhere / shard.name)
    return len(ScenarioDataset(root))


# ---- generic CSV / highD


def _generic_csv(tmp: Path, drop: str | None = None, jump: bool = False, kmh: bool = False) -> tuple[Path, Path]:
    import pandas as pd

    rows = []
    for a, (y, v) in enumerate(((-1.75, 10.0), (1.75, 12.0))):
        for k in range(121):  # 12 s at 10 Hz
            x = 5.0 + v * k * 0.1 + (400.0 if jump and a == 0 and k >= 15 else 0.0)
            rows.append({"scene_id": "s0", "frame": k, "time_s": k * 0.1, "agent_id": f"a{a}", "agent_type": "vehicle",
                         "x_m": x, "y_m": y, "yaw_rad": 0.0, "speed_mps": v * (3.6 if kmh else 1.0), "length_m": 4.5, "width_m": 1.8})
    df = pd.DataFrame(rows)
    if drop:
        df = df.drop(columns=[drop])
    tracks = tmp / "tracks.csv"
    df.to_csv(tracks, index=False)
    mp = []
    for pid, (kind, y) in enumerate((("lane_centre", -1.75), ("lane_centre", 1.75), ("road_edge", -3.5), ("road_edge", 3.5))):
        for x in (0.0, 200.0, 700.0):
            mp.append({"polyline_id": f"p{pid}", "kind": kind, "x_m": x, "y_m": y,
                       "speed_limit_mps": 13.9 if kind == "lane_centre" else 0.0, "width_m": 3.5 if kind == "lane_centre" else 0.0})
    mpath = tmp / "map.csv"
    pd.DataFrame(mp).to_csv(mpath, index=False)
    return tracks, mpath


def _load_generic(**kw):
    def run(tmp: Path):
        from r1sim_sumo.data.logged import load_generic_csv

        t, m = _generic_csv(tmp, **kw)
        return load_generic_csv(t, m, stride_steps=10)
    return run


def _check_csv_jump(scs) -> str:
    ids = sorted({i for sc in scs for i in sc.agents.ids.tolist()})
    assert "a0~1" in ids, ids
    for sc in scs:
        sc.validate(check_jumps=True)  # no state is interpolated across the jump
    return f"teleport split: agents {ids} over {len(scs)} windows; every window passes validate(check_jumps=True)"


def _highd(tmp: Path, drop: str | None = None, speed_limit: float = 33.33, kmh: bool = False) -> Path:
    import pandas as pd

    fr = 25.0
    pd.DataFrame([{"id": 1, "frameRate": fr, "locationId": 2, "speedLimit": speed_limit,
                   "upperLaneMarkings": "8.0;11.5;15.0", "lowerLaneMarkings": "20.0;23.5;27.0"}]).to_csv(tmp / "01_recordingMeta.csv", index=False)
    n = int(12 * fr)
    pd.DataFrame([{"id": i, "width": 4.5, "height": 1.8, "initialFrame": 1, "finalFrame": n, "numFrames": n,
                   "class": "Car", "drivingDirection": 2} for i in (1, 2)]).to_csv(tmp / "01_tracksMeta.csv", index=False)
    rows = []
    for i, (y, v) in ((1, (20.9, 25.0)), (2, (24.4, 30.0))):
        for f in range(1, n + 1):
            rows.append({"frame": f, "id": i, "x": 10.0 + v * f / fr, "y": y, "width": 4.5, "height": 1.8,
                         "xVelocity": v * (3.6 if kmh else 1.0), "yVelocity": 0.0})
    df = pd.DataFrame(rows)
    if drop:
        df = df.drop(columns=[drop])
    df.to_csv(tmp / "01_tracks.csv", index=False)
    return tmp


def _load_highd(**kw):
    def run(tmp: Path):
        from r1sim_sumo.data.logged import load_highd

        return load_highd(_highd(tmp, **kw), 1, stride_steps=20)
    return run


# ---- configs


def _load_pretrain_cfg(text: str):
    def run(tmp: Path):
        from r1sim_sumo.config import load_config
        from r1sim_sumo.train.pretrain import PretrainConfig

        p = tmp / "pretrain.yaml"
        p.write_text(text)
        return load_config(PretrainConfig, p)
    return run


def _load_grpo_cfg(text: str):
    def run(tmp: Path):
        from r1sim_sumo.config import load_config
        from r1sim_sumo.train.grpo import GRPOConfig

        p = tmp / "grpo.yaml"
        p.write_text(text)
        return load_config(GRPOConfig, p)
    return run


# ---- checkpoints and training state


class _Payload:
    """Unpickling this creates a marker file: proof that a loader executed pickle code."""

    marker: Path | None = None

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def _pickle_bomb(path: Path, marker: Path) -> None:
    p = _Payload()
    p.marker = marker
    with open(path, "wb") as f:
        pickle.dump({"model.weight": p}, f)


def _ckpt_pickle(tmp: Path):
    """Weights file replaced by a pickle whose unpickling would create ``PWNED``; the size/hash record updated to match."""
    import hashlib

    from r1sim_sumo.model.checkpoint import load_checkpoint

    d = fx.toy_checkpoint(tmp / "ckpt", agent_layers=1, map_layers=1)
    marker = tmp / "PWNED"
    w = d / "model.safetensors"
    _pickle_bomb(w, marker)
    meta = json.loads((d / "checkpoint.json").read_text())
    meta["weights"] = {"file": w.name, "bytes": w.stat().st_size, "sha256": hashlib.sha256(w.read_bytes()).hexdigest()}
    (d / "checkpoint.json").write_text(json.dumps(meta))
    try:
        return load_checkpoint(d)
    finally:
        if marker.exists():
            raise AssertionError("the pickle payload ran: a checkpoint loader unpickled data")


def _state_pickle(tmp: Path):
    import torch

    from r1sim_sumo.train.train_state import load_train_state, save_train_state

    model = torch.nn.Linear(3, 2)
    opt = torch.optim.AdamW(model.parameters())
    d = save_train_state(tmp / "state", model, opt, {"step": 3})
    marker = tmp / "PWNED"
    _pickle_bomb(d / "state.safetensors", marker)
    try:
        return load_train_state(d, model, opt)
    finally:
        if marker.exists():
            raise AssertionError("the pickle payload ran: load_train_state unpickled data")


def _state_truncated(tmp: Path):
    import torch

    from r1sim_sumo.train.train_state import load_train_state, save_train_state

    model = torch.nn.Linear(3, 2)
    opt = torch.optim.AdamW(model.parameters())
    d = save_train_state(tmp / "state", model, opt, {"step": 3})
    _truncate_copy(d / "state.safetensors", d / "state.safetensors", 0.6)
    return load_train_state(d, model, opt)


def _state_shapes(tmp: Path):
    import torch

    from r1sim_sumo.train.train_state import load_train_state, save_train_state

    d = save_train_state(tmp / "state", torch.nn.Linear(3, 2), torch.optim.AdamW(torch.nn.Linear(3, 2).parameters()), {"step": 3})
    other = torch.nn.Linear(4, 2)
    return load_train_state(d, other, torch.optim.AdamW(other.parameters()))


def _vocab_pickle(tmp: Path):
    from r1sim_sumo.tokens.motion_vocab import MotionVocab

    marker = tmp / "PWNED"
    _pickle_bomb(tmp / "vocab.safetensors", marker)
    try:
        return MotionVocab.load(tmp / "vocab.safetensors")
    finally:
        if marker.exists():
            raise AssertionError("the pickle payload ran: MotionVocab.load unpickled data")


def _npz_pickle(tmp: Path):
    """A shard holding an object array (needs pickle to load) is refused: shards load with allow_pickle=False."""
    from r1sim_sumo.scenario import read_shard, write_shard

    path = write_shard(tmp / "obj.npz", [fx.toy_scenario()])
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["s0/agents/ids"] = np.array([_Payload(), "b", "c", "d"], dtype=object)
    np.savez(tmp / "obj.npz", **arrays)
    return read_shard(tmp / "obj.npz")


# ---- paths


def _safe(relative: str, make_link: bool = False):
    def run(tmp: Path):
        from r1sim_sumo.safe_paths import safe_join

        root = tmp / "out"
        root.mkdir(exist_ok=True)
        if make_link:
            (root / "link").symlink_to(tmp, target_is_directory=True)
        return safe_join(root, relative, "config field 'name'")
    return run


def _controller_step_length(tmp: Path):
    """A SUMO running at 1 s steps is refused by the controller (it needs 0.1 s)."""
    import libsumo

    from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary
    from r1sim_sumo.reliability.fixtures import toy_checkpoint
    from r1sim_sumo.sim.sumo_controller import SumoController

    ensure_sumo_home()
    import r1sim_sumo

    pol = r1sim_sumo.load_policy(toy_checkpoint(tmp / "ck", agent_layers=1, map_layers=1))
    libsumo.start([sumo_binary("sumo"), "-c", str(_bundled("cfg")), "--step-length", "1.0", "--no-step-log", "true"])
    try:
        return SumoController(libsumo, pol)
    finally:
        libsumo.close()


def _check_overlapping(smap) -> str:
    from r1sim_sumo.sim.sumo_controller import LaneLocator

    loc = LaneLocator(smap)
    lane, _d, _h, _s = loc.locate(np.array([[50.0, -1.6], [50.0, -1.6]]), np.array([0.0, math.pi / 2]))
    got = [loc.lane_id[i] for i in lane]
    assert got == ["a_0", "b_0"], got
    return f"read as is ({smap.polylines.num_polylines} polylines); at the crossing the heading picks the lane: {got}"


def _check_zero_length(smap) -> str:
    ids = smap.polylines.lane_id.tolist()
    assert "z_0" not in ids and "a_0" in ids, ids
    return "zero-length lane 'z_0' left out with a logged warning; lane 'a_0' kept"


def _build_cases() -> list[HostileCase]:
    from r1sim_sumo.adapters.sumo_map import MapError
    from r1sim_sumo.commands.simulate import SimulateError
    from r1sim_sumo.config import ConfigError
    from r1sim_sumo.data.logged import LoggedDataError
    from r1sim_sumo.data.sumo_reference import SumoGenerationError
    from r1sim_sumo.model.checkpoint import CheckpointError
    from r1sim_sumo.safe_paths import UnsafePathError
    from r1sim_sumo.scenario import ScenarioError
    from r1sim_sumo.sim.sumo_controller import ControllerError
    from r1sim_sumo.tokens.motion_vocab import VocabError
    from r1sim_sumo.train.train_state import TrainStateError

    net, cfg = "SUMO network", "SUMO config / routes"
    C = HostileCase
    return [
        # ---- SUMO networks
        C("net_truncated", net, "bundled motorway_merge .net.xml cut in half", lambda t: _read_map(_truncate_copy(_bundled("net"), t / "cut.net.xml")),
          MapError, ("cut.net.xml", "netconvert")),
        C("net_garbage", net, "binary garbage named .net.xml", lambda t: (t / "g.net.xml").write_bytes(b"\x00\xff" * 100) and _read_map(t / "g.net.xml"),
          MapError, ("g.net.xml",)),
        C("net_empty", net, "empty (0 byte) .net.xml", lambda t: (t / "e.net.xml").write_text("") or _read_map(t / "e.net.xml"),
          MapError, ("e.net.xml",)),
        C("net_no_drivable_lanes", net, "network whose only lane allows pedestrians", lambda t: _read_map(fx.write_net(t / "p.net.xml", "pedestrian_only")),
          MapError, ("p.net.xml", "no drivable lanes")),
        C("net_zero_length_lane", net, "network with a lane of zero length", lambda t: _read_map(fx.write_net(t / "z.net.xml", "zero_length")),
          None, check=_check_zero_length),
        C("net_overlapping_junctions", net, "two junctions at the same point, a lane crossing another without a junction",
          lambda t: _read_map(fx.write_net(t / "o.net.xml", "overlapping")), None, check=_check_overlapping),
        # ---- .sumocfg / route files (r1sim simulate input checks, SUMO demand reading)
        C("sumocfg_truncated", cfg, "bundled .sumocfg cut in half", lambda t: _resolve_cfg(_truncate_copy(_bundled("cfg"), t / "cut.sumocfg")),
          SimulateError, ("cut.sumocfg", "not valid XML")),
        C("sumocfg_no_net_file", cfg, ".sumocfg without <net-file>", lambda t: _resolve_cfg(_sumocfg(t, "", None)),
          SimulateError, ("x.sumocfg", "net-file")),
        C("sumocfg_missing_net", cfg, ".sumocfg naming a net file that does not exist", lambda t: _resolve_cfg(_sumocfg(t, "nope.net.xml", None)),
          SimulateError, ("x.sumocfg", "input/net-file", "nope.net.xml")),
        C("sumocfg_missing_routes", cfg, ".sumocfg naming a route file that does not exist",
          lambda t: _resolve_cfg(_sumocfg(t, str(_bundled("net")), "nope.rou.xml")), SimulateError, ("x.sumocfg", "input/route-files", "nope.rou.xml")),
        C("routes_truncated_in_sumocfg", cfg, ".sumocfg whose route file is truncated XML",
          lambda t: _resolve_cfg(_sumocfg(t, str(_bundled("net")), _truncate_copy(_bundled("net").with_suffix("").with_suffix(".rou.xml"), t / "cut.rou.xml").name)),
          SimulateError, ("cut.rou.xml", "input/route-files", "not valid XML")),
        C("routes_truncated_generation", cfg, "truncated demand file given to the SUMO reference generator",
          lambda t: _scaled_demand(t), SumoGenerationError, ("cut.rou.xml", "not valid XML")),
        # ---- scenarios
        C("scenario_nan", "scenario", "NaN x position of a valid state", _mutated(lambda s: s.agents.x_m.__setitem__((0, 20), np.nan)),
          ScenarioError, ("scene.npz", "agents.x_m", "veh_0")),
        C("scenario_inf_speed", "scenario", "+inf speed", _mutated(lambda s: s.agents.speed_mps.__setitem__((2, 3), np.inf)),
          ScenarioError, ("scene.npz", "agents.speed_mps")),
        C("scenario_absurd_speed", "scenario", "speed 400 m/s", _mutated(lambda s: s.agents.speed_mps.__setitem__((1, 50), 400.0)),
          ScenarioError, ("scene.npz", "agents.speed_mps", "80")),
        C("scenario_teleport_refused", "scenario", "agent jumps 500 m in 0.1 s, validate(check_jumps=True)", _teleport_refused,
          ScenarioError, ("scene.npz", "agents.x_m/y_m", "veh_1", "split_teleports")),
        C("scenario_teleport_split", "scenario", "agent jumps 500 m in 0.1 s, split_teleports clean-up", _teleport_split, None, check=_check_split),
        C("scenario_duplicate_ids", "scenario", "two agents share an id", _mutated(lambda s: s.agents.ids.__setitem__(1, "veh_0")),
          ScenarioError, ("scene.npz", "agents.ids", "veh_0")),
        C("scenario_zero_agents", "scenario", "no agents at all", _zero_agents, ScenarioError, ("scene.npz", "agents.ids", "zero agents")),
        C("scenario_2000_agents", "scenario", "2000 agents (shard round trip + tokenization)", _many_agents, None, check=_check_many),
        C("manifest_dotdot", "dataset", "manifest shard name '../../outside.npz'", lambda t: _manifest(t, "../../outside.npz"),
          ScenarioError, ("manifest.json", "shards[0].file", "'..'")),
        C("manifest_absolute", "dataset", "manifest shard name '/etc/passwd'", lambda t: _manifest(t, "/etc/passwd"),
          ScenarioError, ("manifest.json", "shards[0].file", "absolute")),
        C("manifest_symlinked_shard", "dataset", "a shard kept elsewhere behind a symlink (allowed on read)", _manifest_symlink_read,
          None, check=lambda n: f"read normally ({n} scenarios): only names in the manifest are restricted"),
        C("shard_object_array", "dataset", "shard with an object (pickled) array", _npz_pickle, ScenarioError, ("obj.npz",)),
        # ---- logged data
        C("csv_missing_column", "logged CSV", "tracks CSV without 'yaw_rad'", _load_generic(drop="yaw_rad"),
          LoggedDataError, ("tracks.csv", "yaw_rad")),
        C("csv_kmh_speeds", "logged CSV", "speeds given in km/h", _load_generic(kmh=True), LoggedDataError, ("tracks.csv", "speed_mps", "km/h")),
        C("csv_teleport_jump", "logged CSV", "agent a0 jumps 400 m between two samples (at 1.5 s)", _load_generic(jump=True), None, check=_check_csv_jump),
        C("highd_missing_column", "highD", "XX_tracks.csv without 'xVelocity'", _load_highd(drop="xVelocity"),
          LoggedDataError, ("01_tracks.csv", "xVelocity")),
        C("highd_speed_limit_kmh", "highD", "speedLimit 130 (km/h) in XX_recordingMeta.csv", _load_highd(speed_limit=130.0),
          LoggedDataError, ("01_recordingMeta.csv", "speedLimit", "km/h")),
        C("highd_velocity_kmh", "highD", "xVelocity in km/h", _load_highd(kmh=True), LoggedDataError, ("01_tracks.csv", "xVelocity")),
        # ---- configs
        C("config_unknown_key", "config", "pretrain YAML with 'learning_rate' (unknown)", _load_pretrain_cfg("lr: 0.001\nlearning_rate: 3\n"),
          ConfigError, ("pretrain.yaml", "learning_rate")),
        C("config_wrong_type", "config", "pretrain YAML with max_steps: 'many'", _load_pretrain_cfg("max_steps: many\n"),
          ConfigError, ("pretrain.yaml", "max_steps")),
        C("config_bad_model_override", "config", "pretrain YAML with model_overrides: {hidden: 3} (unknown model key)",
          _load_pretrain_cfg("model_overrides:\n  hidden: 3\n"), ConfigError, ("pretrain.yaml", "hidden")),
        C("config_bad_sampler", "config", "GRPO YAML with sampler: 'topk:lots'", _load_grpo_cfg("sampler: topk:lots\n"),
          ConfigError, ("grpo.yaml", "topk:lots")),
        # ---- unsafe artefacts
        C("checkpoint_pickle_payload", "artefact", "weights file replaced by a pickle with a code payload (hash record updated)",
          _ckpt_pickle, CheckpointError, ("model.safetensors", "not a readable safetensors")),
        C("train_state_pickle_payload", "artefact", "training state replaced by a pickle with a code payload", _state_pickle,
          TrainStateError, ("state", "unreadable")),
        C("train_state_truncated", "artefact", "training state safetensors cut at 60 %", _state_truncated, TrainStateError, ("state", "unreadable")),
        C("train_state_shapes", "artefact", "training state of another model (shape mismatch)", _state_shapes,
          TrainStateError, ("state", "do not match")),
        C("vocab_pickle_payload", "artefact", "vocabulary file replaced by a pickle with a code payload", _vocab_pickle,
          VocabError, ("vocab.safetensors", "not a readable safetensors")),
        C("path_dotdot", "paths", "config name '../../etc/cron.d/x'", _safe("../../etc/cron.d/x"), UnsafePathError, ("'..'", "config field 'name'")),
        C("path_absolute", "paths", "config name '/etc/passwd'", _safe("/etc/passwd"), UnsafePathError, ("absolute",)),
        C("path_symlink_escape", "paths", "name through a symlink pointing out of the root", _safe("link/escaped.txt", make_link=True),
          UnsafePathError, ("symlink",)),
        # ---- simulator input
        C("controller_step_length", "SUMO controller", "SUMO started with --step-length 1.0", _controller_step_length,
          ControllerError, ("step length", "--step-length 0.1")),
    ]


def _scaled_demand(tmp: Path):
    from r1sim_sumo.data.sumo_reference import write_scaled_demand

    src = _truncate_copy(_bundled("net").with_suffix("").with_suffix(".rou.xml"), tmp / "cut.rou.xml")
    return write_scaled_demand(src, tmp / "out.rou.xml", 1.0, 900.0)


CASES: list[HostileCase] = []


def cases() -> list[HostileCase]:
    """The table (built on first use: it imports the modules under test)."""
    if not CASES:
        import dataclasses

        logging.getLogger("r1sim_sumo.adapters.sumo_map").setLevel(logging.WARNING)
        needs_sumo = ("net_", "controller_")  # sumolib / libsumo
        CASES.extend(dataclasses.replace(c, marks=("sumo",)) if c.name.startswith(needs_sumo) else c for c in _build_cases())
    return CASES
