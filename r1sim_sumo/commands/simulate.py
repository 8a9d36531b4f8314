"""``r1sim simulate``: run a SUMO scenario with the learned policy driving the background traffic.

Examples::

    r1sim simulate                                   # bundled motorway_merge, shipped checkpoint, 300 s
    r1sim simulate --network urban_grid --control fraction=0.5 --end 120 --json out.json
    r1sim simulate --sumocfg my.sumocfg --control vtype=car_idm --fcd-output fcd.xml
    r1sim simulate --native                          # SUMO only, same demand, for comparison
    r1sim simulate --network motorway_merge lane_drop --seeds 0 1 2 --workers 2 --end 60    # batch: 6 runs
    r1sim simulate --batch 'scenarios/*.sumocfg' --seeds 0 1 --backend ray --workers 64 --json runs.json

Settings forced on the configuration (listed by ``--help`` and printed at start, :data:`FORCED_SETTINGS`):
step length 0.1 s, ``--begin 0``, ``--end`` = ``--end`` + 1 s, ``--seed``, teleports off (``--time-to-teleport
-1``), collision detection ``--collision.action warn --collision.mingap-factor 0 --collision.check-junctions``,
warnings written to a log that the summary counts by kind (``warnings``) instead of printing them.
libsumo is used unless ``--traci`` or ``--gui`` (sumo-gui runs through TraCI and needs a DISPLAY).

**Batch mode**: several ``--sumocfg`` / ``--network`` values, ``--batch FILE_OR_GLOB`` (a glob of .sumocfg
files, or a text file listing one .sumocfg per line) and/or ``--seeds S1 S2 ...`` run one simulation per
(config, seed) on a worker pool (``--workers N --backend local|process|ray``; libsumo = one simulation per
process) and print one summary row per run (``--json`` then holds the list of summaries). A loaded checkpoint is
sent to each worker once (``shared``); ``--untrained`` policies are built in the worker from the run's seed, as in a
single run.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import time
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass
from pathlib import Path

from r1sim_sumo.sim.stat_fields import legend

HELP = "run SUMO with the policy driving the background vehicles (drop-in controller) and print a summary"
DEFAULT_NETWORK = "motorway_merge"
DEFAULT_END_S = 300.0
FORCED_SETTINGS = (
    ("--step-length", "0.1", "one 10 Hz policy state per SUMO step"),
    ("--begin", "0", "the run starts at 0 s"),
    ("--end", "<--end> + 1", "the run length of --end"),
    ("--seed", "<--seed>", "same demand draw for native and policy runs"),
    ("--time-to-teleport", "-1", "no teleports: a jam stays visible"),
    ("--collision.action", "warn", "colliding vehicles stay (collisions are counted, not removed)"),
    ("--collision.mingap-factor", "0", "a collision is a touch, not a min-gap violation"),
    ("--collision.check-junctions", "true", "collisions inside junctions count too"),
    ("--error-log", "<temporary file>", "SUMO warnings counted by kind in the summary"),
)


def forced_settings_text() -> str:
    """One line per setting this command forces on the user's .sumocfg."""
    return "\n".join(f"  {k} {v}  ({why})" for k, v, why in FORCED_SETTINGS)


class SimulateError(ValueError):
    """Bad input of ``r1sim simulate``; the message names the file or option and a fix."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = "settings forced on the SUMO configuration (--sumocfg or bundled):\n" + forced_settings_text()
    src = p.add_mutually_exclusive_group()
    src.add_argument("--sumocfg", nargs="+", help="SUMO configuration file(s) (.sumocfg) to run")
    src.add_argument("--network", nargs="+", help=f"bundled network name(s) (default {DEFAULT_NETWORK})")
    src.add_argument("--batch", default=None, metavar="FILE_OR_GLOB",
                     help="batch mode: a glob of .sumocfg files or a text file listing one .sumocfg per line")
    p.add_argument("--checkpoint", default=None, help="policy checkpoint name or path (default: the shipped one)")
    p.add_argument("--untrained", action="store_true",
                   help="use a randomly initialised nano policy on a synthetic vocabulary (smoke tests; meaningless behaviour)")
    p.add_argument("--control", default="all", help="all | vtype=<id>[,<id>] | fraction=<0..1> | id=<regex> (default all)")
    p.add_argument("--sampler", default=None,
                   help="token sampler of the policy (default: the drive's own. commands: quantile:0.7,0.1, the most "
                        "likely token among those ending within 0.1 m of the 0.7 quantile of the policy's forward "
                        "travel, deterministic, docs/simulate/quantile_s53; position: median:0.1, the same around the "
                        "median travel, docs/simulate/sampler_s47. greedy: the most likely token; topk:5 as on the "
                        "model card drives slower and collides more here, docs/simulate/sampler_s32; intent:0.25 is greedy "
                        "but may draw a move to the side the vehicle's route needs with the policy's own probability "
                        "of it, docs/simulate/gate_s42)")
    p.add_argument("--drive", default="commands", choices=["commands", "position"],
                   help="commands (default): the policy's plans become speed and lane-change commands that SUMO "
                        "executes with its own checks (route, signals, right of way, safe gaps); position: vehicles "
                        "are placed on the planned paths (exact, with the --safety layer)")
    p.add_argument("--lane-changes", default="policy+overtaking", choices=["policy", "policy+overtaking"],
                   help="commands drive: policy+overtaking (default): the policy's lane-change requests, and SUMO's "
                        "own speed-gain changes while the policy asks for none; policy: only the policy's (plus those "
                        "SUMO needs for the route or to let a vehicle merge)")
    p.add_argument("--merge-cooperation", default="on", choices=["on", "off"],
                   help="commands drive: on (default): a controlled vehicle that blocks a vehicle SUMO says urgently "
                        "needs its lane (an on-ramp's end, a turn lane) is driven by SUMO until it has made room and "
                        "regained its speed; off: speed commands always stand, and on-ramp vehicles can stand at the "
                        "end of an acceleration lane (docs/simulate/merge_cooperation_s49)")
    p.add_argument("--brake-floor", default="off", choices=["off", "open-road"],
                   help="position drive: open-road: on the open road (far from the end of lanes that only go straight "
                        "on) a plan is followed braking no harder than the vehicle type's comfortable deceleration "
                        "(the policy's plans brake at up to 16 m/s^2); off (default): the plan's braking as it is "
                        "(open-road: more arrivals and speed, more collision events; docs/simulate/position_s39)")
    p.add_argument("--lane-change-gate", default="sumo", choices=["sumo", "off"],
                   help="position drive with the safety layer: sumo (default): a plan enters the lane beside only "
                        "where SUMO's lane-change model finds the change safe (no blocking leader or follower), "
                        "otherwise it is held inside its lane; off: not checked (docs/simulate/gate_s42)")
    p.add_argument("--along-lane", default="on", choices=["on", "off"],
                   help="position drive with the safety layer: on (default): planned boxes the safety layer moves back "
                        "inside their lane (lane-change gate, the carriageway's left edge) point along it, and a vehicle "
                        "heading more than 45 degrees off its lane away from the lane's ends is handed to SUMO; inside a "
                        "junction where lanes only split (a bay's taper) planned boxes stay in the vehicle's internal "
                        "lane (session 66); off: none of these (before session 65; docs/simulate/along_lane_s65)")
    p.add_argument("--junction-turns", default="sumo", choices=["sumo", "policy"],
                   help="position drive with the safety layer: sumo (default): a vehicle inside a junction whose plan "
                        "leaves its route (the policy has no route input), or whose route turns off the major road "
                        "there (onto a road of lower SUMO priority: a roundabout's exits), is driven through the "
                        "junction by SUMO and taken back on its route's next edge; policy: it stays the policy's, "
                        "snapped onto its route's lane (docs/simulate/junction_turns_s60, roundabout_s61)")
    p.add_argument("--junction-crossings", default=None, choices=["sumo", "policy"],
                   help="default: the drive's own (sumo for both drives). Commands drive: sumo lets SUMO "
                        "drive the speed inside a junction where the vehicle may have to stop and from the same "
                        "distance before it. Position drive (also with --safety none): sumo: SUMO drives a vehicle through a junction "
                        "where it may have to stop (a signal, a link without priority, a turn or links that cross), "
                        "from max(20 m, 3 s x its allowed speed) before the stop line, and the policy takes it back on "
                        "its route's next edge; policy: the policy drives up to and through it, the safety layer "
                        "stopping it for red lights and foes (docs/simulate/junction_sumo_s63)")
    p.add_argument("--junction-floor", type=float, default=0.0, metavar="M/S",
                   help="commands drive: the least speed commanded to a controlled vehicle inside a junction (SUMO's "
                        "checks still stop it behind its leader, for foes and at red lights), so that a policy vehicle "
                        "does not stand in a junction by its own choice; 0: off (default; 2.0 cost game/ramp 2-4%% of "
                        "its arrivals, docs/simulate/junction_floor_s48)")
    p.add_argument("--free-road-quantile", type=float, default=None, metavar="Q",
                   help="with a median / quantile sampler: a controlled vehicle with nothing within 100 m ahead to slow "
                        "for (no leader, signal, turn, yield or slower road) is decoded at this quantile of its travel "
                        "(e.g. 0.7), the others at the sampler's own; off by default (docs/simulate/free_road_s55)")
    p.add_argument("--free-road-headway", type=float, default=None, metavar="SECONDS",
                   help="with --free-road-quantile: a leader at least this headway ahead (+ 2.5 m) and not slower "
                        "leaves the road free (default: any leader within 100 m does not)")
    p.add_argument("--speed-carry", default=None, choices=["off", "gains", "free", "both"],
                   help="gains: read each token's speed change against what the vehicle drove over its last 0.5 s "
                        "where it is faster now, so that the token that repeats it keeps the speed now instead of "
                        "giving back half of a speed-up; free: the same on a free road only (no leader within 1.5 s, "
                        "signal, turn or yield within 100 m); both: slow-downs too; off: each plan ends at its "
                        "token's end pose, as before session 58 (default: each drive's own, gains in both, off in "
                        "the position drive with --safety none; docs/simulate/speed_carry_s58)")
    p.add_argument("--guidance", type=float, default=0.0, metavar="W",
                   help="desired-speed guidance weight (classifier-free guidance on the policy's desired-speed input; "
                        "0 = off, the default; costs a second policy step per decision; see README)")
    p.add_argument("--replan-every", type=float, default=0.5, metavar="SECONDS",
                   help="time between the policy's decisions, 0.1-0.5 s in steps of 0.1 (default 0.5: one per 0.5 s "
                        "token); shorter (commands drive only) replans from the last 1.1 s and drives only the plan's "
                        "first steps: quicker answers to the traffic at 2.2-2.4x the run time for 0.2 "
                        "(docs/simulate/replan_s44)")
    p.add_argument("--plot", default=None, metavar="PNG",
                   help="write a time-space picture (position along the busiest route vs time, coloured by speed)")
    p.add_argument("--standstill-handoff", type=float, default=5.0, metavar="SECONDS",
                   help="hand a vehicle standing this long to SUMO until it moves again (default 5; 0 = never)")
    p.add_argument("--safety", default="krauss", choices=["krauss", "none"],
                   help="krauss (default): policy paths (position drive) and speed commands (commands drive, on top of "
                        "SUMO's own checks) no faster than a Krauss safe speed behind the vehicle ahead; none: the raw policy")
    p.add_argument("--end", type=float, default=DEFAULT_END_S, help=f"simulated seconds (default {DEFAULT_END_S:g})")
    p.add_argument("--seed", type=int, default=0, help="SUMO --seed and policy sampler seed (default 0)")
    p.add_argument("--seeds", type=int, nargs="+", default=None, help="batch mode: one run per seed (replaces --seed)")
    p.add_argument("--gui", action="store_true", help="run sumo-gui (needs a DISPLAY)")
    p.add_argument("--traci", action="store_true", help="use TraCI (a SUMO process) instead of libsumo")
    p.add_argument("--native", action="store_true", help="no policy: SUMO drives every vehicle (comparison)")
    p.add_argument("--fcd-output", default=None, help="write SUMO floating-car data (10 Hz) to this file")
    p.add_argument("--json", default=None, help="write the summary as JSON to this file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from r1sim_sumo.workers import add_pool_arguments

    add_pool_arguments(p, default_workers=1, what="simulations (batch mode)")


# ---------------------------------------------------------------------------- inputs


def resolve_sumocfg(sumocfg: str | None, network: str | None) -> Path:
    """The .sumocfg to run, checked: exists, parses, names a net-file that exists."""
    if sumocfg is None:
        from r1sim_sumo.resources import network_files

        try:
            return network_files(network or DEFAULT_NETWORK)["sumocfg"]
        except FileNotFoundError as exc:
            raise SimulateError(f"--network {network}: {exc}") from exc
    p = Path(sumocfg)
    if not p.is_file():
        raise SimulateError(f"--sumocfg {p}: file not found; pass an existing SUMO configuration (.sumocfg)")
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as exc:
        raise SimulateError(f"--sumocfg {p}: not valid XML ({exc})") from exc
    net = root.find("./input/net-file")
    if net is None or not net.get("value"):
        raise SimulateError(f"--sumocfg {p}: no <input><net-file value=...> entry; a configuration must name its network")
    for name in net.get("value").split(","):
        f = (p.parent / name.strip()) if not Path(name.strip()).is_absolute() else Path(name.strip())
        if not f.is_file():
            raise SimulateError(f"--sumocfg {p}: field input/net-file names '{name.strip()}', which does not exist ({f})")
    routes = root.find("./input/route-files")
    for name in (routes.get("value") or "").split(",") if routes is not None else []:
        if not name.strip():
            continue
        f = (p.parent / name.strip()) if not Path(name.strip()).is_absolute() else Path(name.strip())
        if not f.is_file():
            raise SimulateError(f"--sumocfg {p}: field input/route-files names '{name.strip()}', which does not exist ({f})")
        if f.suffix != ".gz":
            try:
                ET.parse(f)
            except ET.ParseError as exc:
                raise SimulateError(f"--sumocfg {p}: route file {f} (field input/route-files) is not valid XML ({exc}); "
                                    "repair or regenerate it") from exc
    return p


def load_checkpoint_arg(name: str | None):
    """``r1sim_sumo.load_policy(name)`` with a clear error when there is no such checkpoint."""
    import r1sim_sumo

    try:
        return r1sim_sumo.load_policy(name)
    except (FileNotFoundError, ImportError) as exc:
        what = f"checkpoint '{name}'" if name else "the shipped default checkpoint"
        raise SimulateError(f"--checkpoint: {what} not found ({type(exc).__name__}: {exc}); pass a checkpoint folder "
                            "with --checkpoint PATH (train one with `r1sim pretrain`), or --untrained / --native") from exc


# ---------------------------------------------------------------------------- running


def simulate(cfg: Path, args, policy=None, progress: bool = True) -> dict:
    """Run SUMO for ``args.end`` seconds (with the controller unless ``policy is None``); returns the summary."""
    from r1sim_sumo._sumo_env import ensure_sumo_home
    from r1sim_sumo.sumo_launch import sumo_command

    ensure_sumo_home()
    use_traci = bool(args.traci or args.gui)
    if use_traci:
        import traci as conn
    else:
        import libsumo as conn
    import tempfile

    log_dir = tempfile.TemporaryDirectory(prefix="r1sim_simulate_")
    cmd = sumo_command(args.seed, sumocfg=cfg, end_s=float(args.end) + 1.0, fcd_output=args.fcd_output, gui=args.gui,
                       error_log=Path(log_dir.name) / "sumo_warnings.log")
    try:
        with _quiet_stderr(not use_traci):
            conn.start(cmd)
    except Exception as exc:  # noqa: BLE001 - SUMO reports config errors as generic exceptions
        raise SimulateError(f"{cfg}: SUMO failed to start ({type(exc).__name__}: {exc}); command: {' '.join(cmd)}") from exc
    try:
        ctrl = None
        if policy is not None:
            from r1sim_sumo.rollout.samplers import parse_sampler
            from r1sim_sumo.sim.sumo_controller import ControllerError, SumoController

            try:
                if args.sampler is not None:
                    parse_sampler(args.sampler)
            except ValueError as exc:
                raise SimulateError(f"--sampler {args.sampler}: {exc}; e.g. quantile:0.7,0.1, median:0.1, greedy, topk:5, entropy:16,80, intent:0.25") from exc
            try:
                ctrl = SumoController(conn, policy, control=args.control, sampler=args.sampler, seed=args.seed,
                                     safety=getattr(args, "safety", "krauss"), drive=getattr(args, "drive", "commands"),
                                     standstill_handoff_s=getattr(args, "standstill_handoff", 5.0),
                                     lane_changes=getattr(args, "lane_changes", "policy+overtaking"),
                                     guidance=getattr(args, "guidance", 0.0),
                                     merge_cooperation=getattr(args, "merge_cooperation", "on") == "on",
                                     brake_floor=getattr(args, "brake_floor", "off"),
                                     lane_change_gate=getattr(args, "lane_change_gate", "sumo"),
                                     along_lane=getattr(args, "along_lane", "on") == "on",
                                     junction_turns=getattr(args, "junction_turns", "sumo"),
                                     junction_crossings=getattr(args, "junction_crossings", None),
                                     replan_every_s=getattr(args, "replan_every", 0.5),
                                     junction_floor_mps=getattr(args, "junction_floor", 0.0),
                                     free_road_quantile=getattr(args, "free_road_quantile", None),
                                     free_road_headway_s=getattr(args, "free_road_headway", None),
                                     speed_carry=getattr(args, "speed_carry", None))
            except ControllerError as exc:
                raise SimulateError(f"--control/--drive/--lane-changes/--guidance/--replan-every/--junction-floor/"
                                    f"--free-road-quantile/--free-road-headway: {exc}") from exc
        n = int(round(float(args.end) / 0.1))
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=n, unit="step", desc="native" if ctrl is None else "policy", leave=False)
        native = _NativeStats()
        from r1sim_sumo.sim.free_road_speed import FreeRoadSpeed

        free_road = FreeRoadSpeed(conn)  # every vehicle in a native run, the policy's in a policy run
        ts = None
        if getattr(args, "plot", None):
            from r1sim_sumo.sim.time_space import TimeSpaceRecorder

            ts = TimeSpaceRecorder(conn)
        t0 = time.perf_counter()
        crashed, done = None, 0
        try:
            for k in range(n):
                with _quiet_stderr(not use_traci):
                    conn.simulationStep()
                if ctrl is not None:
                    ctrl.step()
                    free_road.step(ctrl.stats, ctrl.controlled_ids)
                else:
                    native.step(conn)
                    free_road.step(native.s, conn.vehicle.getIDList)
                if ts is not None:
                    ts.step()
                done = k + 1
                if bar is not None and k % 50 == 49:
                    bar.update(50)
                    if ctrl is not None:
                        bar.set_postfix(veh=ctrl.stats.running, ctrl=ctrl.stats.controlled_now)
        except Exception as exc:  # noqa: BLE001 - only SUMO's own failures are turned into a partial summary
            if not _is_sumo_failure(exc):
                raise
            crashed = f"{type(exc).__name__}: {exc}".strip()
            if ctrl is not None:  # the step stopped half-way: count running vehicles from the controller's records
                ctrl.stats.running = len(ctrl.vehicles)
        wall = time.perf_counter() - t0
        if bar is not None:
            bar.close()
        st = ctrl.stats if ctrl is not None else native.s
        st.warnings.update(count_warnings(Path(log_dir.name) / "sumo_warnings.log"))
        s = st.summary()
        if ts is not None:
            title = f"{cfg.stem} native" if ctrl is None else f"{cfg.stem} policy, {ctrl.drive}"
            if ctrl is not None and ctrl.drive == "position" and ctrl.safety is None:
                title += ", no safety layer"
            s["time_space"] = ts.save(Path(args.plot), title)
        s.update(mode="native" if ctrl is None else "policy", sumocfg=str(cfg), wall_s=wall,
                 sim_s_per_wall_s=(done * 0.1) / max(wall, 1e-9), end_s=float(args.end), seed=int(args.seed),
                 interface="traci" if use_traci else "libsumo", completed_steps=done)
        if ctrl is not None:  # which drive and token rule drove the policy (the sampler default depends on the drive)
            s.update(drive=ctrl.drive, sampler=ctrl.driver.sampler.spec)
        if crashed is not None:
            s["sumo_crashed"] = crashed
            # a TraCIException is SUMO refusing one call (bad id, unknown lane), not SUMO dying: say which
            what = "a TraCI call failed" if crashed.startswith("TraCIException") else "SUMO stopped responding"
            raise SumoCrashed(f"{cfg}: {what} after {done * 0.1:.1f} of {float(args.end):g} simulated s "
                              f"({crashed}); the summary below covers the part that ran", s)
        return s
    finally:
        try:  # the controller's close() lets libsumo forget its last moveToXY first (sumo_launch.settle_remote_control)
            if ctrl is not None:
                ctrl.close()
            else:
                conn.close()
        except Exception:  # noqa: BLE001 - a crashed SUMO cannot be closed cleanly; nothing is left to release
            pass
        log_dir.cleanup()


def write_json(path: str | Path, payload: dict) -> None:
    """Write a run summary (or ``{"runs": [...], ...}``) as JSON, with ``"legend"``: what every counter of
    :class:`~r1sim_sumo.sim.sumo_controller.ControllerStats` means and its unit, so the file explains itself."""
    # torch-heavy, imported where it runs (docs/architecture.md, imports)
    from r1sim_sumo.sim.sumo_controller import ControllerStats

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps({**payload, "legend": legend(ControllerStats)}, indent=2, default=str))


WARNING_KINDS = (  # (kind, regular expression on a SUMO warning line); the first match wins
    ("emergency_braking", r"emergency braking"),
    ("collision", r"collision"),
    ("teleport", r"teleport"),
    ("insertion", r"insert|could not be inserted|depart"),
    ("no_connection", r"no connection|no valid route|unreachable"),
    ("lane_change", r"lane ?change|changeLane"),
    ("move_to_xy", r"moveToXY|could not map"),
    ("signal", r"traffic light|tls"),
)


def count_warnings(log: Path) -> dict:
    """SUMO warnings in the error log, counted by kind (:data:`WARNING_KINDS`, else ``other``)."""
    import re
    from collections import Counter

    out: Counter = Counter()
    if not log.is_file():
        return {}
    with log.open(errors="replace") as f:
        for line in f:
            if not line.startswith("Warning:"):
                continue
            low = line.lower()
            out[next((k for k, rx in WARNING_KINDS if re.search(rx, low, re.IGNORECASE)), "other")] += 1
    return dict(out)


class _quiet_stderr:
    """Silence the C++ stderr of libsumo during a call (its warnings go to the error log and are counted);
    Python's own stderr (progress bar, errors) is unaffected. No-op for TraCI (a separate process)."""

    def __init__(self, active: bool):
        self.active = active

    def __enter__(self):
        if self.active:
            sys.stderr.flush()
            self._saved = os.dup(2)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 2)
            os.close(devnull)
        return self

    def __exit__(self, *exc):
        if self.active:
            os.dup2(self._saved, 2)
            os.close(self._saved)
        return False


class SumoCrashed(SimulateError):
    """SUMO died (or the TraCI connection broke) during the run; ``summary`` holds the counters up to then."""

    def __init__(self, message: str, summary: dict):
        super().__init__(message)
        self.summary = summary


def _is_sumo_failure(exc: BaseException) -> bool:
    """A TraCI/libsumo error (connection closed, SUMO process killed, simulation error), not a bug of ours."""
    mod = type(exc).__module__ or ""
    return mod.startswith(("traci", "libsumo", "sumolib")) or isinstance(exc, (ConnectionError, BrokenPipeError))


class _NativeStats:
    """The same population / speed / insertion / collision counters for a SUMO-only run (no controller): collision
    events by the same :class:`~r1sim_sumo.sim.collision_events.CollisionCounter` as the controller's."""

    def __init__(self) -> None:
        from r1sim_sumo.sim.collision_events import CollisionCounter
        from r1sim_sumo.sim.queue_growth import QueueGrowthTracker
        from r1sim_sumo.sim.sumo_controller import STILL_SPEED_MPS, ControllerStats, StandstillTracker

        self.s = ControllerStats()
        self.collisions = CollisionCounter(check_sat=True)
        self.standstill = StandstillTracker()
        self.queues = QueueGrowthTracker(STILL_SPEED_MPS)
        self.prev: dict[str, tuple[float, float]] = {}

    def step(self, conn) -> None:
        from r1sim_sumo.adapters.sumo_state import read_vehicle_states
        from r1sim_sumo.sim.sumo_controller import STILL_SPEED_MPS

        s = self.s
        s.steps += 1
        s.sim_seconds += 0.1
        s.departed += conn.simulation.getDepartedNumber()
        s.arrived += conn.simulation.getArrivedNumber()
        s.teleports += conn.simulation.getStartingTeleportNumber()
        s.loaded += conn.simulation.getLoadedNumber()
        s.waiting_to_insert = len(conn.simulation.getPendingVehicles())
        s.waiting_to_insert_max = max(s.waiting_to_insert_max, s.waiting_to_insert)
        states = read_vehicle_states(conn)
        n = self.collisions.update(conn, states)
        s.collisions_sumo += n.sumo
        s.collisions_sat += n.sat
        s.collisions_any += n.either
        self.collisions.list_new_events(s.collision_events, conn, s.sim_seconds)
        cur = {}
        for v, x, y in zip(states.ids, states.x_m.tolist(), states.y_m.tolist(), strict=True):
            cur[v] = (x, y)
            if v in self.prev:
                px, py = self.prev[v]
                s.vkm_all += ((x - px) ** 2 + (y - py) ** 2) ** 0.5 / 1000.0
        s.speed_sum_mps += float(states.speed_mps.sum())
        s.standing_steps += int((abs(states.speed_mps) < STILL_SPEED_MPS).sum())
        self.standstill.update(s, states.ids, states.speed_mps)
        self.queues.update(s, conn, states.ids, states.speed_mps, s.sim_seconds, s.waiting_to_insert)
        s.vehicle_steps += len(cur)
        self.prev = cur
        s.running = len(cur)
        removed = s.departed - s.arrived - s.running
        if removed != s.removed:
            s.removals["while_sumo_driven"] += removed - s.removed
        s.removed = removed

    def summary(self) -> dict:
        return self.s.summary()


def format_summary(s: dict) -> str:
    share = s.get("completed_route_share")
    rows = [
        ("mode / interface", f"{s['mode']} / {s['interface']}"),
        *([("drive / token sampler", f"{s['drive']} / {s['sampler']}")] if s.get("drive") else []),
        ("simulated [s]", f"{s['sim_seconds']:.1f}"),
        ("vehicles departed / arrived / running / removed", f"{s['departed']} / {s['arrived']} / {s['running']} / {s['removed']}"),
        ("waiting to insert (now / most)", f"{s.get('waiting_to_insert', 0)} / {s.get('waiting_to_insert_max', 0)}"),
        ("arrived of those that left", _pct(s.get("arrived_of_left_share"))),
        ("removals by reason", ", ".join(f"{k}={v}" for k, v in sorted(s.get("removals", {}).items())) or "0"),
        ("standing vehicle share (< 0.3 m/s)", _pct(s.get("standing_share"))),
        ("longest standstill [s] / vehicles standing > 60 s", f"{s.get('longest_standstill_s', 0):.1f} / {s.get('stood_over_60s', 0)}"),
        ("longest queue growth [s] (head) / queues growing > 60 s",
         f"{s.get('longest_queue_growth_s', 0):.0f} ({s.get('longest_queue_head') or '-'}) / {s.get('queues_grown_over_60s', 0)}"),
        ("vehicles controlled (ever / now)", f"{s['controlled_total']} / {s['controlled_now']}"),
        ("mean speed [m/s]", f"{s['mean_speed_mps']:.2f}"),
        ("vehicle-km (all / controlled)", f"{s['vkm_all']:.2f} / {s['vkm_controlled']:.2f}"),
        ("collisions SUMO / SAT / either", f"{s['collisions_sumo']} / {s['collisions_sat']} / {s['collisions_any']}"),
        ("collisions per 1000 veh-km", f"{s['collisions_per_1000_vkm']:.1f}"),
        ("drive", s.get("drive") or "-"),
        ("SUMO overruled: speed capped / lane changes refused",
         f"{_pct(s.get('speed_capped_share'))} of {s.get('speed_commands', 0)} / {s.get('lane_change_refused', 0)} of "
         f"{s.get('lane_change_requests', 0)}"),
        ("lane changes: the policy's / SUMO's own", f"{s.get('lane_changes_policy', 0)} / {s.get('lane_changes_sumo', 0)}"),
        ("SUMO drove the speed: route merges / yields to merging vehicles [vehicle-decisions]",
         f"{s.get('route_merge_decisions', 0)} / {s.get('merge_yields', 0)}"),
        ("safety-filter slowdowns [vehicle-steps] / rule stops",
         f"{s.get('safety_slowdowns', 0)} / " + (", ".join(f"{k}={v}" for k, v in sorted(s.get("rule_stops", {}).items())) or "0")),
        ("SUMO warnings by kind", ", ".join(f"{k}={v}" for k, v in sorted(s.get("warnings", {}).items())) or "0"),
        ("policy share of vehicle-km / retakes after standstill",
         f"{'n/a' if s.get('policy_vkm_share') is None else format(s['policy_vkm_share'], '.2f')} / {s.get('retakes', 0)}"),
        ("offroad events", f"{s['offroad']}"),
        ("handbacks", ", ".join(f"{k}={v}" for k, v in sorted(s["handbacks"].items())) or "0"),
        ("teleports", f"{s['teleports']}"),
        ("controlled vehicles that completed their route", "n/a" if share is None else f"{100 * share:.1f} %"),
        ("simulated seconds per wall second", f"{s['sim_s_per_wall_s']:.1f}"),
    ]
    w = max(len(r[0]) for r in rows)
    return "\n".join(f"{k:<{w}}  {v}" for k, v in rows)


def _pct(x) -> str:
    return "n/a" if x is None else f"{100 * x:.1f} %"


def run(args: argparse.Namespace) -> int:
    if batch_requested(args):
        return run_batch(args)
    try:
        if args.gui and not os.environ.get("DISPLAY"):
            raise SimulateError("--gui: no DISPLAY is set, sumo-gui cannot open a window; run without --gui "
                                "(or set DISPLAY / use xvfb-run)")
        if args.end <= 0:
            raise SimulateError(f"--end {args.end}: must be a positive number of seconds")
        cfg = resolve_sumocfg(args.sumocfg[0] if args.sumocfg else None, args.network[0] if args.network else None)
        if args.native:
            policy = None
        elif args.untrained:
            from r1sim_sumo.model.untrained import untrained_policy

            policy = untrained_policy(seed=args.seed)
        else:
            policy = load_checkpoint_arg(args.checkpoint)
        if policy is not None:
            import torch

            torch.set_num_threads(min(torch.get_num_threads(), 2))
        print("r1sim simulate: settings forced on the configuration:\n" + forced_settings_text(), file=sys.stderr)
        summary = simulate(cfg, args, policy, progress=not args.no_progress)
    except SumoCrashed as exc:
        print(f"r1sim simulate: error: {exc}", file=sys.stderr)
        print(format_summary(exc.summary))
        if args.json:
            write_json(args.json, exc.summary)
            print(f"partial summary written to {args.json}")
        return 3
    except SimulateError as exc:
        print(f"r1sim simulate: error: {exc}", file=sys.stderr)
        return 2
    print(format_summary(summary))
    if args.json:
        write_json(args.json, summary)
        print(f"summary written to {args.json}")
    return 0


# ---------------------------------------------------------------------------- batch mode


GLOB_CHARS = set("*?[")


@dataclass
class SimRun:
    """One batch run: the .sumocfg, the seed and the options every run shares (see ``r1sim simulate``)."""

    sumocfg: str
    seed: int
    end: float
    control: str
    sampler: str | None  # None: the drive's default
    traci: bool
    native: bool
    untrained: bool
    fcd_output: str | None
    drive: str = "commands"
    safety: str = "krauss"
    standstill_handoff: float = 5.0
    lane_changes: str = "policy+overtaking"
    guidance: float = 0.0
    merge_cooperation: str = "on"
    brake_floor: str = "off"
    lane_change_gate: str = "sumo"
    replan_every: float = 0.5
    junction_floor: float = 0.0
    free_road_quantile: float | None = None
    free_road_headway: float | None = None
    speed_carry: str | None = None
    junction_turns: str = "sumo"
    junction_crossings: str | None = None
    along_lane: str = "on"

    def describe(self) -> str:
        return f"{self.sumocfg} seed {self.seed}"


def batch_requested(args: argparse.Namespace) -> bool:
    """True for several configs, a ``--batch`` file/glob or ``--seeds``."""
    many = len(args.sumocfg or []) > 1 or len(args.network or []) > 1
    return bool(many or args.batch or args.seeds)


def _batch_configs(spec: str) -> list[str]:
    """A glob of .sumocfg files, one .sumocfg, or a text file listing .sumocfg paths (relative to it)."""
    if GLOB_CHARS & set(spec):
        found = sorted(glob.glob(spec, recursive=True))
        if not found:
            raise SimulateError(f"--batch {spec}: the pattern matches no file")
        return found
    p = Path(spec)
    if not p.is_file():
        raise SimulateError(f"--batch {spec}: no such file (give a glob of .sumocfg files or a text file listing them)")
    if p.suffix == ".sumocfg":
        return [str(p)]
    lines = [ln.split("#", 1)[0].strip() for ln in p.read_text().splitlines()]
    out = [str(Path(ln) if Path(ln).is_absolute() else p.parent / ln) for ln in lines if ln]
    if not out:
        raise SimulateError(f"--batch {spec}: the file lists no .sumocfg (one path per line expected)")
    return out


def batch_runs(args: argparse.Namespace) -> list[SimRun]:
    """Every (config, seed) run of the batch, configs checked up front (errors name the file and field)."""
    if args.gui:
        raise SimulateError("--gui: batch mode runs many simulations without windows; drop --gui or run one config")
    if args.batch:
        cfgs = [resolve_sumocfg(c, None) for c in _batch_configs(args.batch)]
    elif args.sumocfg:
        cfgs = [resolve_sumocfg(c, None) for c in args.sumocfg]
    else:
        cfgs = [resolve_sumocfg(None, n) for n in (args.network or [None])]
    seeds = list(dict.fromkeys(args.seeds or [args.seed]))
    runs = []
    for cfg in cfgs:
        for seed in seeds:
            fcd = None
            if args.fcd_output:
                f = Path(args.fcd_output)
                fcd = str(f.with_name(f"{f.stem}__{cfg.stem}__seed{seed}{f.suffix or '.xml'}"))
            runs.append(SimRun(str(cfg), int(seed), float(args.end), args.control, args.sampler, bool(args.traci),
                               bool(args.native), bool(args.untrained), fcd, getattr(args, "drive", "commands"),
                               getattr(args, "safety", "krauss"), getattr(args, "standstill_handoff", 5.0),
                               getattr(args, "lane_changes", "policy+overtaking"), getattr(args, "guidance", 0.0),
                               getattr(args, "merge_cooperation", "on"), getattr(args, "brake_floor", "off"),
                               getattr(args, "lane_change_gate", "sumo"), getattr(args, "replan_every", 0.5),
                               getattr(args, "junction_floor", 0.0), getattr(args, "free_road_quantile", None),
                               getattr(args, "free_road_headway", None), getattr(args, "speed_carry", None),
                               getattr(args, "junction_turns", "sumo"), getattr(args, "junction_crossings", None),
                               getattr(args, "along_lane", "on")))
    labels = [(r.sumocfg, r.seed) for r in runs]
    if len(set(labels)) != len(labels):
        raise SimulateError("batch: the same (sumocfg, seed) is listed twice; each run must be unique")
    return runs


def simulate_task(run: SimRun, policy=None) -> dict:
    """Pool task: one simulation; ``policy`` is the shared checkpoint (``None``: native or untrained)."""
    from r1sim_sumo.model.untrained import untrained_policy  # torch: ~1 s, kept out of `r1sim --help`

    if run.untrained and not run.native:
        policy = untrained_policy(seed=run.seed)
    if run.native:
        policy = None
    ns = argparse.Namespace(gui=False, **{k: v for k, v in asdict(run).items() if k not in ("sumocfg", "native", "untrained")})
    try:
        return simulate(Path(run.sumocfg), ns, policy, progress=False)
    except SumoCrashed as exc:  # a partial summary is still a result: the row says where SUMO stopped
        return exc.summary


ROW_FIELDS = [("sumocfg", "{}"), ("seed", "{}"), ("mode", "{}"), ("drive", "{}"), ("departed", "{}"),
              ("waiting_to_insert", "{}"), ("arrived", "{}"),
              ("collisions_any", "{}"), ("teleports", "{}"), ("mean_speed_mps", "{:.2f}"), ("sim_s_per_wall_s", "{:.1f}")]


def format_rows(summaries: list[dict]) -> str:
    """A fixed-width table: one row per run (``crashed`` marks runs where SUMO stopped early)."""
    head = [k for k, _ in ROW_FIELDS] + ["status"]
    rows = []
    for s in summaries:
        cells = [fmt.format(Path(s[k]).stem if k == "sumocfg" else s.get(k, "")) for k, fmt in ROW_FIELDS]
        rows.append(cells + ["crashed" if s.get("sumo_crashed") else "ok"])
    w = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    line = lambda cells: "  ".join(c.ljust(w[i]) for i, c in enumerate(cells))  # noqa: E731
    return "\n".join([line(head), line(["-" * x for x in w]), *(line(r) for r in rows)])


def run_batch(args: argparse.Namespace) -> int:
    """``r1sim simulate`` batch mode: run, print one row per run and the pool's retry report."""
    from r1sim_sumo.workers import TaskFailedError, pool_from_args

    try:
        runs = batch_runs(args)
        policy = None if (args.native or args.untrained) else load_checkpoint_arg(args.checkpoint)
        with pool_from_args(args) as pool:
            summaries = pool.map(simulate_task, runs, shared=policy)
            stats = pool.stats
    except (SimulateError, TaskFailedError, ValueError, ImportError) as exc:
        print(f"r1sim simulate: error: {exc}", file=sys.stderr)
        return 2
    print(format_rows(summaries))
    print(f"[simulate] {len(runs)} run(s); {stats.summary()}")
    if args.json:
        write_json(args.json, {"runs": summaries, "pool": stats.to_dict()})
        print(f"summaries written to {args.json}")
    return 3 if any(s.get("sumo_crashed") for s in summaries) else 0
