"""SUMO reference generation: windows, determinism, alignment, parallel jobs, failures, saved states."""

from __future__ import annotations

import contextlib
import json
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from r1sim_sumo.data.dataset import GenerationError, generate_sumo_dataset
from r1sim_sumo.data.sumo_reference import (
    SumoGenConfig,
    SumoGenerationError,
    generate_sumo_scenarios,
    resolve_network,
    write_scaled_demand,
)
from r1sim_sumo.scenario import CURRENT_INDEX, N_WINDOW_10HZ, ScenarioDataset

pytestmark = pytest.mark.sumo

NET = "motorway_merge"


def _cfg(network=NET, seed=0, **kw) -> SumoGenConfig:
    kw = {"duration_s": 30.0, "warmup_s": 20.0, **kw}
    return SumoGenConfig(network=network, seed=seed, **kw)


@pytest.fixture(scope="module")
def run_seed0():
    return generate_sumo_scenarios(_cfg(seed=0))


def test_short_run_gives_validated_91_step_windows(run_seed0):
    cfg = _cfg()
    assert len(run_seed0) == cfg.num_windows() == (300 - N_WINDOW_10HZ) // 20 + 1
    for w, sc in enumerate(run_seed0):
        sc.validate()
        assert sc.num_steps == N_WINDOW_10HZ and sc.current_index == CURRENT_INDEX
        assert sc.agents.valid[:, CURRENT_INDEX].all()  # agents = vehicles present now
        assert sc.map.tl_state.shape == (sc.map.num_polylines, N_WINDOW_10HZ)
        m = sc.metadata
        assert (m["source"], m["network"], m["seed"], m["window_index"]) == ("sumo", NET, 0, w)
        assert m["start_time_s"] == pytest.approx(20.0 + 2.0 * w)
        assert "generator_version" in m
    # vehicles enter and leave a motorway stretch within 9.1 s: some tracks are partially valid
    valid = np.concatenate([sc.agents.valid for sc in run_seed0])
    assert (~valid).any() and valid.all(axis=1).any()
    # speeds are plausible motorway speeds, yaw in radians
    sc = run_seed0[-1]
    spd = sc.agents.speed_mps[sc.agents.valid]
    assert 5.0 < spd.mean() < 45.0


def test_same_seed_identical_different_seed_differs(run_seed0):
    again = generate_sumo_scenarios(_cfg(seed=0))
    assert len(again) == len(run_seed0)
    for a, b in zip(again, run_seed0, strict=True):
        assert a.agents.ids.tolist() == b.agents.ids.tolist()
        for f in ("x_m", "y_m", "yaw_rad", "speed_mps", "valid"):
            np.testing.assert_array_equal(getattr(a.agents, f), getattr(b.agents, f))
        np.testing.assert_array_equal(a.map.tl_state, b.map.tl_state)
    other = generate_sumo_scenarios(_cfg(seed=1))
    a, b = other[0].agents, run_seed0[0].agents
    assert a.ids.tolist() != b.ids.tolist() or not np.array_equal(a.x_m, b.x_m)


def test_windows_are_aligned_by_stride(run_seed0):
    stride = 20
    checked = 0
    for prev, cur in zip(run_seed0[:-1], run_seed0[1:], strict=True):
        idx_prev = {v: i for i, v in enumerate(prev.agents.ids.tolist())}
        for j, vid in enumerate(cur.agents.ids.tolist()):
            i = idx_prev.get(vid)
            if i is None or not prev.agents.valid[i, CURRENT_INDEX + stride]:
                continue
            for f in ("x_m", "y_m", "yaw_rad", "speed_mps"):
                assert getattr(cur.agents, f)[j, CURRENT_INDEX] == getattr(prev.agents, f)[i, CURRENT_INDEX + stride]
            # the whole overlap (71 steps) agrees, valid mask included
            np.testing.assert_array_equal(cur.agents.x_m[j, : N_WINDOW_10HZ - stride], prev.agents.x_m[i, stride:])
            np.testing.assert_array_equal(cur.agents.valid[j, : N_WINDOW_10HZ - stride], prev.agents.valid[i, stride:])
            checked += 1
    assert checked > 20


def test_traffic_lights_recorded_on_signalised_network():
    sc = generate_sumo_scenarios(_cfg("urban_intersection", seed=0, duration_s=9.1, warmup_s=5.0))
    assert len(sc) == 1
    tl = sc[0].map.tl_state
    assert tl.shape[1] == N_WINDOW_10HZ
    assert (tl > 0).any()  # some lanes carry a signal state


def test_scaled_demand(tmp_path):
    src = resolve_network(NET).route_file
    dst = write_scaled_demand(src, tmp_path / "d.rou.xml", factor=2.0, end_s=1500.0, vtype_probabilities={"truck": 0.5})
    flows_src = {f.get("id"): f for f in ET.parse(src).getroot().iter("flow")}
    for f in ET.parse(dst).getroot().iter("flow"):
        rate = float(f.get("period")[4:-1])
        assert rate == pytest.approx(2.0 * float(flows_src[f.get("id")].get("period")[4:-1]), rel=1e-5)
        assert float(f.get("end")) == 1500.0
    truck = [v for v in ET.parse(dst).getroot().iter("vType") if v.get("id") == "truck"][0]
    assert float(truck.get("probability")) == 0.5
    with pytest.raises(SumoGenerationError, match="nosuchtype"):
        write_scaled_demand(src, tmp_path / "e.rou.xml", 1.0, 100.0, vtype_probabilities={"nosuchtype": 1.0})
    assert {f.get("departSpeed") for f in ET.parse(dst).getroot().iter("flow")} == {"max"}  # the network's own
    slow = write_scaled_demand(src, tmp_path / "r.rou.xml", 1.0, 100.0, depart_speed="random")
    assert {f.get("departSpeed") for f in ET.parse(slow).getroot().iter("flow")} == {"random"}


def test_parallel_dataset_sorted_and_failing_job_leaves_no_manifest(tmp_path):
    cfgs = [_cfg("lane_drop", seed=3, duration_s=12.0, warmup_s=5.0), _cfg(NET, seed=1, duration_s=12.0, warmup_s=5.0),
            _cfg(NET, seed=0, duration_s=12.0, warmup_s=5.0)]
    out = generate_sumo_dataset(cfgs, tmp_path / "ok", workers=2, progress=False)
    man = json.loads((out / "manifest.json").read_text())
    assert [j["label"] for j in man["jobs"]] == ["lane_drop__seed00003", f"{NET}__seed00000", f"{NET}__seed00001"]
    ds = ScenarioDataset(out)
    assert len(ds) == man["num_scenarios"] == 3 * 2
    assert [(s.metadata["network"], s.metadata["seed"]) for s in ds] == [("lane_drop", 3)] * 2 + [(NET, 0)] * 2 + [(NET, 1)] * 2
    # refusing to overwrite
    with pytest.raises(GenerationError, match="refusing to overwrite"):
        generate_sumo_dataset(cfgs[:1], out, workers=1, progress=False)

    # a broken network: the job fails, the error names network and seed, nothing is left behind
    bad = tmp_path / "broken_net"
    bad.mkdir()
    (bad / "broken_net.net.xml").write_text("<net><edge id='x'")
    (bad / "broken_net.sumocfg").write_text("<configuration/>")
    (bad / "broken_net.rou.xml").write_text("<routes/>")
    with pytest.raises(GenerationError, match=r"broken_net' seed 7"):
        generate_sumo_dataset([cfgs[0], _cfg(str(bad), seed=7)], tmp_path / "fail", workers=2, progress=False)
    assert not (tmp_path / "fail").exists()


def test_saved_state_restores_window_current_step(tmp_path):
    from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary

    ensure_sumo_home()
    import libsumo

    from r1sim_sumo.adapters.sumo_state import clear_static_cache, read_vehicle_states

    scs = generate_sumo_scenarios(_cfg(seed=2, duration_s=11.1, warmup_s=10.0, save_states=True), state_root=tmp_path)
    assert len(scs) == 2
    sc = scs[1]
    state = tmp_path / sc.metadata["state_file"]
    assert state.exists() and sc.metadata["state_time_s"] == pytest.approx(sc.metadata["start_time_s"] + 1.0)
    src = resolve_network(NET)
    libsumo.start([sumo_binary(), "-n", str(src.net_file), "--step-length", "0.1", "--no-step-log", "true",
                   "--no-warnings", "true"])
    try:
        clear_static_cache()
        libsumo.simulation.loadState(str(state))
        st = read_vehicle_states(libsumo)
    finally:
        libsumo.close()
    a = sc.agents
    order = {v: i for i, v in enumerate(st.ids.tolist())}
    assert sorted(order) == sorted(a.ids.tolist())
    idx = [order[v] for v in a.ids.tolist()]
    np.testing.assert_allclose(st.x_m[idx], a.x_m[:, CURRENT_INDEX], atol=0.01)
    np.testing.assert_allclose(st.y_m[idx], a.y_m[:, CURRENT_INDEX], atol=0.01)


def test_recorder_splits_tracks_on_reappearance_and_jumps():
    from types import SimpleNamespace

    from r1sim_sumo.data.sumo_reference import TrackRecorder

    def states(ids, xs):
        n = len(ids)
        z = np.zeros(n)
        return SimpleNamespace(ids=np.array(ids), agent_type=np.zeros(n, np.int8), length_m=z + 4.5, width_m=z + 1.8,
                               x_m=np.array(xs, float), y_m=z, yaw_rad=z, speed_mps=z + 10, vx_mps=z + 10, vy_mps=z)

    rec = TrackRecorder()
    seq = [(["a", "b"], [0.0, 50.0]), (["a", "b"], [1.0, 51.0]), (["b"], [52.0]),  # a vanishes (teleport)
           (["a", "b"], [90.0, 53.0]), (["a", "b"], [91.0, 200.0])]  # a reappears; b jumps 147 m
    for ids, xs in seq:
        rec.add(states(ids, xs), np.zeros(3, np.int8))
    run = rec.finish()
    assert run.track_ids.tolist() == ["a", "b", "a~1", "b~1"]
    assert run.track.tolist() == [0, 1, 0, 1, 1, 2, 1, 2, 3]
    assert run.tl_state.shape == (5, 3)


def test_slowdowns_brake_then_release_and_are_reproducible():
    """Brake-hold-release events: vehicles drop well below their speed, then SUMO drives them back up; same seed,
    same events; rate 0 changes nothing."""
    from r1sim_sumo.data.sumo_reference import RunStats, iter_sumo_scenarios

    def run(rate, seed=3):
        st = RunStats()
        scs = list(iter_sumo_scenarios(_cfg(seed=seed, duration_s=40.0, slowdowns_per_vehicle_hour=rate), stats=st))
        return scs, st.extra["slowdown_events"]

    plain, n0 = run(0.0)
    again, n0b = run(0.0)
    slowed, n1 = run(400.0)
    slowed_b, n1b = run(400.0)
    assert n0 == n0b == 0 and n1 == n1b and n1 > 5
    assert "slowdowns_per_vehicle_hour" not in plain[0].metadata and slowed[0].metadata["slowdowns_per_vehicle_hour"] == 400.0
    assert np.array_equal(slowed[-1].agents.x_m, slowed_b[-1].agents.x_m)
    assert np.array_equal(plain[-1].agents.x_m, again[-1].agents.x_m)

    def accel_events(scs):  # agent-steps accelerating > 1 m/s^2 from below 15 m/s on this motorway
        n = 0
        for sc in scs:
            a = sc.agents
            v = np.hypot(a.vx_mps, a.vy_mps)
            dv = (v[:, 1:] - v[:, :-1]) / 0.1
            ok = a.valid[:, 1:] & a.valid[:, :-1]
            n += int((ok & (v[:, :-1] < 15.0) & (dv > 1.0)).sum())
        return n

    assert accel_events(slowed) > 3 * max(accel_events(plain), 1)
    with pytest.raises(ValueError, match="slowdowns_per_vehicle_hour"):
        _cfg(slowdowns_per_vehicle_hour=-1.0)


@contextlib.contextmanager
def _generator_sumo_20s_in(seed: int = 5):
    """libsumo running the reference generator's SUMO command on NET (its demand, ``seed``), 200 steps (20 s) in;
    closed afterwards. For driving an event injector step by step."""
    import libsumo

    from r1sim_sumo.data.sumo_reference import demand_factor, generation_command

    cfg = _cfg(seed=seed, duration_s=30.0)
    src = resolve_network(cfg.network)
    with tempfile.TemporaryDirectory() as tmp:
        routes = write_scaled_demand(src.route_file, Path(tmp) / "d.rou.xml", demand_factor(cfg), 60.0, None, None, None)
        libsumo.start(generation_command(src, routes, cfg))
        try:
            for _ in range(200):
                libsumo.simulationStep()
            yield libsumo
        finally:
            libsumo.close()


def _injector_runs(rate_key: str, events_key: str, min_events: int, network: str = NET, duration_s: float = 40.0):
    """An event injector of the reference generator at rate 0 and twice at 600 per vehicle-hour (seed 3): rate 0 makes
    no event and leaves no metadata, the same seed gives the same events and trajectories. Returns the scenarios at
    rate 0 and at 600."""
    from r1sim_sumo.data.sumo_reference import RunStats, iter_sumo_scenarios

    def run(rate):
        st = RunStats()
        scs = list(iter_sumo_scenarios(_cfg(network=network, seed=3, duration_s=duration_s, **{rate_key: rate}),
                                       stats=st))
        return scs, st.extra[events_key]

    (plain, n0), (on, n1), (on_b, n1b) = run(0.0), run(600.0), run(600.0)
    assert n0 == 0 and n1 == n1b and n1 > min_events
    assert rate_key not in plain[0].metadata
    assert on[0].metadata[rate_key] == 600.0
    assert np.array_equal(on[-1].agents.x_m, on_b[-1].agents.x_m)
    return plain, on


def test_close_ups_shorten_headways_then_restore_them_reproducibly():
    """Tailgate-then-reopen events: followers get closer to their leaders than SUMO's 1 s headway ever allows, the
    driver's own headway comes back afterwards, the same seed gives the same events and rate 0 changes nothing."""
    from r1sim_sumo.data.close_ups import CloseUpInjector, CloseUpSettings

    _injector_runs("close_ups_per_vehicle_hour", "close_up_events", 5)

    # the driver's own tau comes back after the hold: drive one event through libsumo directly
    inj = CloseUpInjector(CloseUpSettings(1e6, hold_s=(1.0, 1.0)), seed=5, step_s=0.1)  # every eligible vehicle, 1 s
    with _generator_sumo_20s_in() as libsumo:
        own = {v: libsumo.vehicle.getTau(v) for v in libsumo.vehicle.getIDList()}
        inj.before_step(libsumo)
        changed = [v for v in own if libsumo.vehicle.getTau(v) < 0.6]
        assert changed and all(own[v] >= 0.9 for v in changed)
        inj.settings.rate_per_vehicle_hour = 0.0  # no new events: the ones under way still end
        for _ in range(10):
            libsumo.simulationStep()
            inj.before_step(libsumo)
        still = set(libsumo.vehicle.getIDList())
        assert all(abs(libsumo.vehicle.getTau(v) - own[v]) < 1e-9 for v in changed if v in still)
    with pytest.raises(ValueError, match="close_ups_per_vehicle_hour"):
        _cfg(close_ups_per_vehicle_hour=-1.0)
    with pytest.raises(ValueError, match="tau_s"):
        CloseUpSettings(10.0, tau_s=(0.05, 0.3))


def test_desired_speed_steps_lower_then_restore_the_speed_factor_at_a_window_and_drivers_speed_up():
    """Desired-speed steps: a driver's speedFactor drops for a while and its own comes back just before a recorded
    window's current index, so windows hold drivers steady below their recorded desired speed that then speed up;
    the same seed gives the same events, rate 0 changes nothing, and bad settings name the field."""
    from r1sim_sumo.data.desired_steps import LEAD_MAX_STEPS, DesiredStepInjector, DesiredStepSettings

    plain, stepped = _injector_runs("desired_steps_per_vehicle_hour", "desired_step_events", 20,
                                    network="motorway_merge", duration_s=60.0)

    def steady_below_then_up(scs):  # at the current index: steady over 1 s, desired > 3 m/s above, +0.8 m/s^2 next 2 s
        n = 0
        for sc in scs:
            a, t0 = sc.agents, 10
            ok = a.valid[:, t0] & a.valid[:, t0 - 10] & a.valid[:, t0 + 20]
            v0 = a.speed_mps[:, t0]
            n += int((ok & (np.abs(v0 - a.speed_mps[:, t0 - 10]) < 0.5) & (v0 > 5) & (a.desired_speed_mps - v0 > 3)
                      & ((a.speed_mps[:, t0 + 20] - v0) / 2 > 0.8)).sum())
        return n

    assert steady_below_then_up(stepped) > 3 * max(steady_below_then_up(plain), 1)

    # one event driven through libsumo: the factor drops, and its own comes back 0..4 steps before a window step
    windows = np.arange(100, 2000, 20, dtype=np.int64)
    inj = DesiredStepInjector(DesiredStepSettings(1e6, factor=(0.5, 0.5), hold_s=(1.0, 1.0)), seed=5, step_s=0.1,
                              restore_at=windows)
    with _generator_sumo_20s_in() as libsumo:
        own = {v: libsumo.vehicle.getSpeedFactor(v) for v in libsumo.vehicle.getIDList()}
        inj.before_step(libsumo)  # its step 0
        changed = [v for v in own if abs(libsumo.vehicle.getSpeedFactor(v) - 0.5 * own[v]) < 1e-9]
        assert changed
        ends = sorted(inj._ends)  # all started with a 1 s hold: each ends 0..4 steps before a window step
        assert ends and all(e >= 10 and min(windows[windows >= e] - e) <= LEAD_MAX_STEPS for e in ends)
        inj.settings.rate_per_vehicle_hour = 0.0  # no new events: the ones under way still end
        for _ in range(ends[-1] + 1):
            libsumo.simulationStep()
            inj.before_step(libsumo)
        still = set(libsumo.vehicle.getIDList())
        assert all(abs(libsumo.vehicle.getSpeedFactor(v) - own[v]) < 1e-9 for v in changed if v in still)
    with pytest.raises(ValueError, match="desired_steps_per_vehicle_hour"):
        _cfg(desired_steps_per_vehicle_hour=-1.0)
    with pytest.raises(ValueError, match="desired_step_factor"):
        _cfg(desired_steps_per_vehicle_hour=10.0, desired_step_factor=(0.5, 1.2))


def test_windows_record_sumos_desired_speed_and_the_compact_dataset_keeps_it(run_seed0, tmp_path):
    """Each window's agents carry SUMO's desired speed at the current step (lane limit x speedFactor, capped by the
    type's maxSpeed), the input the drop-in controller hands the policy; tokenizing and the compact dataset keep it."""
    from tests.test_policy_history import compact_and_reference

    for sc in run_seed0:
        a, ci = sc.agents, sc.current_index
        d = np.asarray(a.desired_speed_mps)
        assert d.shape == (a.num_agents,) and np.isfinite(d).all()
        assert (d > 5.0).all() and (d < 60.0).all()
        assert (a.speed_mps[:, ci] <= d + 0.5).all()  # Krauss never drives above the desired speed
    assert len({round(float(v), 3) for sc in run_seed0 for v in sc.agents.desired_speed_mps}) > 5  # speedFactor spread
    scs = run_seed0[:4]
    comp, ref = compact_and_reference(scs, tmp_path)
    for i, sc in enumerate(scs):
        got = comp[i].agents.desired_speed()
        assert np.array_equal(got, ref[i].agents.desired_speed())
        idx = np.asarray(ref[i].agent_index)
        assert np.array_equal(got, np.asarray(sc.agents.desired_speed_mps, np.float32)[idx])
        assert np.array_equal(comp.noised(i, 3, np.random.default_rng(i)).agents.desired_speed(), got)


def _max_lateral_step_m(cfg: SumoGenConfig, steps: int) -> float:
    """Largest sideways move of any vehicle within one 0.1 s step [m] (across its heading), driving ``cfg`` in libsumo."""
    import math
    import tempfile
    from pathlib import Path

    import libsumo

    from r1sim_sumo.data.sumo_reference import (
        demand_factor,
        generation_command,
        resolve_network,
        write_scaled_demand,
    )

    src = resolve_network(cfg.network)
    worst, prev = 0.0, {}
    with tempfile.TemporaryDirectory() as tmp:
        routes = write_scaled_demand(src.route_file, Path(tmp) / "d.rou.xml", demand_factor(cfg), 200.0, None, None, None)
        libsumo.start(generation_command(src, routes, cfg))
        try:
            for _ in range(steps):
                libsumo.simulationStep()
                for v in libsumo.vehicle.getIDList():
                    x, y = libsumo.vehicle.getPosition(v)
                    a = math.radians(90.0 - libsumo.vehicle.getAngle(v))  # SUMO degrees clockwise from north -> radians
                    if v in prev:
                        worst = max(worst, abs(-(x - prev[v][0]) * math.sin(a) + (y - prev[v][1]) * math.cos(a)))
                    prev[v] = (x, y)
        finally:
            libsumo.close()
    return worst


def test_lanechange_duration_turns_one_step_lane_jumps_into_continuous_moves():
    """SUMO's default lane change moves a vehicle a lane width (3.2 m) within one step; with
    ``lanechange_duration_s`` = 2 it crosses over 2 s (~0.16 m per step), which 0.5 s tokens can follow."""
    jump = _max_lateral_step_m(_cfg(network="lane_drop", seed=1, duration_s=150.0), 1500)
    smooth = _max_lateral_step_m(_cfg(network="lane_drop", seed=1, duration_s=150.0, lanechange_duration_s=2.0), 1500)
    assert jump > 2.5, jump
    assert smooth < 1.5, smooth
    with pytest.raises(ValueError, match="lanechange_duration_s"):
        _cfg(lanechange_duration_s=-1.0)


def test_overtake_right_reaches_sumo_and_the_recipe_passes_it_on():
    """``overtake_right`` turns SUMO's no-passing-on-the-right rule off (``--lanechange.overtake-right true``) in the
    run SUMO actually starts, and a recipe hands it to every SUMO job; the default keeps SUMO's rule."""
    import tempfile
    from pathlib import Path

    import libsumo

    from r1sim_sumo.data.dataset import DatasetRecipe
    from r1sim_sumo.data.sumo_reference import (
        demand_factor,
        generation_command,
        resolve_network,
        write_scaled_demand,
    )

    for flag, expect in ((True, "true"), (False, "false")):
        cfg = _cfg(network="lane_drop", seed=1, duration_s=10.0, overtake_right=flag)
        src = resolve_network(cfg.network)
        with tempfile.TemporaryDirectory() as tmp:
            routes = write_scaled_demand(src.route_file, Path(tmp) / "d.rou.xml", demand_factor(cfg), 20.0, None, None, None)
            libsumo.start(generation_command(src, routes, cfg))
            try:
                assert libsumo.simulation.getOption("lanechange.overtake-right") == expect
            finally:
                libsumo.close()
    jobs = DatasetRecipe(networks=("lane_drop",), heldout_networks=(), train_seeds=1, val_seeds=1, test_seeds=1,
                         highway_envs=(), overtake_right=True).jobs()
    assert all(j.overtake_right for split in jobs.values() for j in split)
