"""Drop-in SUMO controller throughput: simulated seconds per wall second with 50 to 700 policy-driven
vehicles vs SUMO driving the same scene (same run, ratio), peak memory, and where the time goes, for both drives.

Scenes: ``merge`` = bundled ``motorway_merge`` without its demand; ``N`` cars are inserted at t=0 spread over the 3
mainline lanes (1.5 km) at 15 m/s, and every vehicle that arrives is replaced by a new one at the start, so about ``N``
vehicles stay on the road (the run checks that at least 95% of them were inserted); ``grid`` = the 9 x 9 netgenerate
city grid with ~N cars on random trips. Each configuration runs in its own process (libsumo holds one simulation per
process; ``VmHWM`` of that process = peak memory). The policy is the shipped ``r1sim-nano`` with the drop-in's
defaults (sampler, guidance, lane changes), 2 torch threads; ``drive`` is ``commands`` (the default: SUMO executes
speed and lane-change commands) or ``position`` (the vehicles are placed with ``moveToXY`` behind the Krauss safety
filter); off-road hand-back and the standstill hand-off are disabled (``offroad_margin_m`` huge,
``standstill_handoff_s=None``) so that the vehicles stay controlled and the cost of controlling ``N`` is measured
(``mean_controlled``). Rows also time ``moveToXY`` with keepRoute 3 (the position drive's) vs 2.

Run: ``python benchmarks/run.py --only sumo_controller [--quick]`` or this file with ``--worker``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROUTES = """<routes>
  <vType id="car" length="4.6" width="1.8" maxSpeed="50" speedFactor="1"/>
  <route id="r_in" edges="main_in merge main_out"/>
  <route id="r_merge" edges="merge main_out"/>
  <route id="r_out" edges="main_out"/>
</routes>
"""


def _start(n: int, tmp: Path):
    from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary
    from r1sim_sumo.resources import network_files

    ensure_sumo_home()
    import libsumo

    rf = tmp / "bench.rou.xml"
    rf.write_text(ROUTES)
    libsumo.start([sumo_binary("sumo"), "-c", str(network_files("motorway_merge")["sumocfg"]), "--route-files", str(rf),
                   "--step-length", "0.1", "--no-step-log", "true", "--no-warnings", "true", "--time-to-teleport", "-1",
                   "--collision.action", "warn", "--collision.mingap-factor", "0", "--collision.check-junctions", "true",
                   "--seed", "0", "--end", "10000"])
    # spread the N cars evenly over the 3 mainline lanes of all three mainline edges (about 1.5 km)
    edges = [(e, r, libsumo.lane.getLength(f"{e}_0")) for e, r in (("main_in", "r_in"), ("merge", "r_merge"), ("main_out", "r_out"))]
    total = sum(length - 20.0 for _, _, length in edges)
    per_lane = (n + 2) // 3
    gap = total / max(per_lane, 1)
    k = 0
    for lane in range(3):
        for i in range(per_lane):
            if k == n:
                break
            r, s_along = _route_and_offset(edges, i * gap + 0.5 * gap * (lane % 2))  # stagger neighbouring lanes
            libsumo.vehicle.add(f"v{k}", r, typeID="car", depart="now", departLane=str(lane), departPos=f"{10.0 + s_along:.1f}",
                                departSpeed="10")
            k += 1
    libsumo.simulationStep()
    if libsumo.vehicle.getIDCount() < 0.95 * n:
        raise RuntimeError(f"bench_sumo_controller: only {libsumo.vehicle.getIDCount()} of {n} vehicles could be inserted")
    return libsumo


def _route_and_offset(edges, s_along: float) -> tuple[str, float]:
    """The route starting on the edge that holds mainline position ``s_along`` [m], and the offset on that edge."""
    for _edge, route, length in edges[:-1]:
        if s_along < length - 20.0:
            return route, s_along
        s_along -= length - 20.0
    return edges[-1][1], s_along


GRID_SIZE = 9  # the city-scale scene: netgenerate grid 9 x 9 x 100 m, 2 lanes per direction (~46 lane-km)


class GridTrips:
    """The city-scale scene: ``n`` cars on random trips over :func:`large_network` (signalised 9 x 9 grid). At t=0 each
    car starts at a random free position of a random edge (``departPos="random_free"``) on the shortest route to another random
    edge; every car that arrives is replaced by a new random trip, so about ``n`` cars stay on the network. Trips are
    drawn from a seeded generator, so the native and the policy run see the same demand."""

    def __init__(self, conn, n: int, seed: int = 0):
        import random

        self.conn, self.rng, self.added = conn, random.Random(seed), 0
        self.edges = [e for e in conn.edge.getIDList() if not e.startswith(":")]
        conn.vehicletype.copy("DEFAULT_VEHTYPE", "car")
        conn.vehicletype.setLength("car", 4.6)
        conn.vehicletype.setWidth("car", 1.8)
        for _ in range(n):
            self.add(start_anywhere=True)

    def add(self, start_anywhere: bool = False) -> None:
        c = self.conn
        for _ in range(20):  # a random origin-destination pair that has a route
            o, d = self.rng.sample(self.edges, 2)
            route = c.simulation.findRoute(o, d).edges
            if len(route) >= 2:
                break
        rid, vid = f"r{self.added}", f"v{self.added}"
        c.route.add(rid, list(route))
        c.vehicle.add(vid, rid, typeID="car", depart="now", departLane="best",
                      departPos="random_free" if start_anywhere else "base", departSpeed="max")
        self.added += 1

    def refill(self) -> None:
        for _ in self.conn.simulation.getArrivedIDList():
            self.add()


def start_grid(n: int, tmp: Path):
    """libsumo on the city grid with ``n`` random trips (:class:`GridTrips`); returns ``(conn, trips)``."""
    from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary

    ensure_sumo_home()
    import libsumo

    net = large_network(tmp, GRID_SIZE)
    libsumo.start([sumo_binary("sumo"), "-n", str(net), "--step-length", "0.1", "--no-step-log", "true",
                   "--no-warnings", "true", "--time-to-teleport", "-1", "--collision.action", "warn",
                   "--collision.mingap-factor", "0", "--collision.check-junctions", "true", "--seed", "0",
                   "--end", "10000"])
    trips = GridTrips(libsumo, n)
    libsumo.simulationStep()
    return libsumo, trips


class MergeRefill:
    """motorway_merge scene: replace every arrived car by a new one at the start of the mainline."""

    def __init__(self, conn, n: int):
        self.conn, self.added = conn, n

    def refill(self) -> None:
        for _v in self.conn.simulation.getArrivedIDList():
            self.conn.vehicle.add(f"v{self.added}", "r_in", typeID="car", depart="now", departSpeed="10")
            self.added += 1


def start_scene(scene: str, n: int, tmp: Path):
    """``(conn, refiller)`` of the named scene: ``merge`` (motorway_merge, ~N cars on 1.5 km) or ``grid`` (city grid)."""
    if scene == "grid":
        return start_grid(n, tmp)
    conn = _start(n, tmp)
    return conn, MergeRefill(conn, n)


def worker(mode: str, n: int, horizon_s: float, scene: str = "merge", drive: str = "commands") -> dict:
    # isort: off
    import r1sim_sumo  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads, as `r1sim simulate`)
    import torch
    # isort: on

    from r1sim_sumo._memory import peak_rss_mb

    torch.set_num_threads(2)  # as `r1sim simulate`; the target is stated for 2 CPU threads
    with tempfile.TemporaryDirectory() as d:
        conn, refill = start_scene(scene, n, Path(d))
        ctrl = None
        if mode == "policy":
            import r1sim_sumo
            from r1sim_sumo.sim.sumo_controller import SumoController

            ctrl = SumoController(conn, r1sim_sumo.load_policy(), offroad_margin_m=1e9, seed=0, standstill_handoff_s=None,
                                 drive=drive)
        steps = int(round(horizon_s / 0.1))
        t_step, n_veh, n_ctrl = 0.0, 0, 0
        t0 = time.perf_counter()
        for _ in range(steps):
            ts = time.perf_counter()
            conn.simulationStep()
            t_step += time.perf_counter() - ts
            refill.refill()  # keep the population at about n
            if ctrl is not None:
                ctrl.step()
                n_ctrl += ctrl.stats.controlled_now
            n_veh += conn.vehicle.getIDCount()
        wall = time.perf_counter() - t0
        out = {"mode": mode, "drive": drive, "scene": scene, "n": n, "sim_s": steps * 0.1, "wall_s": wall, "sim_s_per_wall_s": steps * 0.1 / wall,
               "mean_vehicles": n_veh / steps, "mean_controlled": n_ctrl / steps, "sumo_step_s": t_step,
               "peak_rss_mib": peak_rss_mb()}
        if ctrl is not None:
            s = ctrl.stats
            out.update(policy_s=s.time_policy_s, read_s=s.time_read_s, move_s=s.time_move_s, checks_s=s.time_checks_s,
                       policy_calls=s.policy_calls, policy_agents_mean=s.policy_agents / max(s.policy_calls, 1),
                       move_us_keeproute3=_move_cost(conn, 3), move_us_keeproute2=_move_cost(conn, 2))
        conn.close()
    return out


def _move_cost(conn, keep_route: int, reps: int = 5) -> float:
    """Mean microseconds per moveToXY call (each vehicle to its own current pose)."""
    ids = conn.vehicle.getIDList()
    poses = [(v, *conn.vehicle.getPosition(v), conn.vehicle.getAngle(v)) for v in ids]
    t0 = time.perf_counter()
    for _ in range(reps):
        for v, x, y, a in poses:
            conn.vehicle.moveToXY(v, "", -1, x, y, a, keep_route)
    return 1e6 * (time.perf_counter() - t0) / max(reps * len(poses), 1)


def large_network(tmp: Path, grid: int = 9, length_m: float = 100.0, lanes: int = 2) -> Path:
    """A ``grid x grid`` signalised city grid (``netgenerate``, ``lanes`` lanes per direction, blocks ``length_m``
    long): 9 x 9 x 100 m x 2 lanes = about 58 lane-km of normal lanes. Returns its .net.xml."""
    from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary

    ensure_sumo_home()
    net = tmp / f"grid{grid}.net.xml"
    subprocess.run([sumo_binary("netgenerate"), "--grid", "--grid.number", str(grid), "--grid.length", f"{length_m:g}",
                    "--default.lanenumber", str(lanes), "--tls.guess", "true", "--no-turnarounds", "true",
                    "-o", str(net)], check=True, capture_output=True)
    return net


def startup_worker(grid: int) -> dict:
    """Build a SumoController on a large generated network; time [s] and this process's peak memory [MiB]
    before and after."""
    # isort: off
    import r1sim_sumo  # first: the OpenMP wait policy before torch loads
    import libsumo
    import torch
    # isort: on
    from r1sim_sumo._memory import peak_rss_mb
    from r1sim_sumo.adapters.sumo_map import read_sumo_map
    from r1sim_sumo.sim.sumo_controller import SumoController

    torch.set_num_threads(2)
    with tempfile.TemporaryDirectory() as d:
        net = large_network(Path(d), grid)
        from r1sim_sumo._sumo_env import sumo_binary

        libsumo.start([sumo_binary("sumo"), "-n", str(net), "--step-length", "0.1", "--no-step-log", "true",
                       "--no-warnings", "true"])
        policy = r1sim_sumo.load_policy()
        lanes = [ln for ln in libsumo.lane.getIDList() if not ln.startswith(":")]
        lane_km = sum(libsumo.lane.getLength(ln) for ln in lanes) / 1000.0
        rss0 = peak_rss_mb()
        t0, c0 = time.perf_counter(), time.process_time()
        ctrl = SumoController(libsumo, policy, seed=0, map_cache_dir=None)  # cold, lazy: tiles encoded when needed
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        t0, c0 = time.perf_counter(), time.process_time()
        SumoController(libsumo, policy, seed=0, map_cache_dir=None, lazy_map=False)  # cold, the whole network
        wall_eager, cpu_eager = time.perf_counter() - t0, time.process_time() - c0
        rss_cold = peak_rss_mb()
        SumoController(libsumo, policy, seed=0, map_cache_dir=Path(d) / "maps")  # fills the map cache
        t0, c0 = time.perf_counter(), time.process_time()
        SumoController(libsumo, policy, seed=0, map_cache_dir=Path(d) / "maps")  # warm: the network seen before
        wall_warm, cpu_warm = time.perf_counter() - t0, time.process_time() - c0
        out = {"grid": grid, "lane_km": lane_km, "map_tokens": int(len(ctrl.driver.map_tokens.polyline)),
               "startup_s": wall, "startup_cpu_s": cpu, "startup_eager_s": wall_eager, "startup_eager_cpu_s": cpu_eager, "startup_warm_s": wall_warm, "startup_warm_cpu_s": cpu_warm,
               "peak_rss_mib_before": rss0, "peak_rss_mib_after": rss_cold,
               "map_polylines": int(len(read_sumo_map(str(net)).polylines.kind))}
        libsumo.close()
    return out


def _spawn(mode: str, n: int, horizon_s: float, scene: str = "merge", drive: str = "commands") -> dict:
    r = subprocess.run([sys.executable, __file__, "--worker", mode, str(n), str(horizon_s), scene, drive],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"worker {mode} n={n} failed:\n{r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def _row(nat: dict, pol: dict) -> dict:
    """One table row: a policy run beside the native run of the same scene (shares of the policy run's wall time)."""
    other = pol["wall_s"] - pol["policy_s"] - pol["read_s"] - pol["move_s"] - pol["checks_s"] - pol["sumo_step_s"]
    return {
        "scene": pol["scene"], "drive": pol["drive"], "vehicles": pol["n"], "mean_vehicles": round(pol["mean_vehicles"], 1),
        "mean_controlled": round(pol["mean_controlled"], 1),
        "policy_sim_s_per_wall_s": round(pol["sim_s_per_wall_s"], 2),
        "native_sim_s_per_wall_s": round(nat["sim_s_per_wall_s"], 1),
        "slowdown_vs_native": round(nat["sim_s_per_wall_s"] / pol["sim_s_per_wall_s"], 1),
        "ms_per_policy_call": round(1000 * pol["policy_s"] / max(pol["policy_calls"], 1), 1),
        "agents_per_call": round(pol["policy_agents_mean"], 1),
        "share_policy_%": round(100 * pol["policy_s"] / pol["wall_s"], 1),
        "share_sumo_step_%": round(100 * pol["sumo_step_s"] / pol["wall_s"], 1),
        "share_read_%": round(100 * pol["read_s"] / pol["wall_s"], 1),
        "share_move_%": round(100 * pol["move_s"] / pol["wall_s"], 1),
        "share_checks_%": round(100 * pol["checks_s"] / pol["wall_s"], 1),
        "share_other_%": round(100 * other / pol["wall_s"], 1),
        "moveToXY_us_keepRoute3": round(pol["move_us_keeproute3"], 1),
        "moveToXY_us_keepRoute2": round(pol["move_us_keeproute2"], 1),
        "peak_rss_mib_policy": round(pol["peak_rss_mib"]), "peak_rss_mib_native": round(nat["peak_rss_mib"]),
    }


def run(quick: bool = False) -> dict:
    scenes = [("merge", 50)] if quick else [("merge", 50), ("merge", 100), ("merge", 200), ("grid", 100), ("grid", 700)]
    horizon = 10.0 if quick else 20.0
    rows = []
    for scene, n in scenes:
        nat = _spawn("native", n, horizon, scene)  # one native run per scene: both drives' ratios are to it
        for drive in ("commands",) if quick or (scene, n) == ("merge", 50) else ("commands", "position"):
            rows.append(_row(nat, _spawn("policy", n, horizon, scene, drive)))
    r = subprocess.run([sys.executable, __file__, "--startup", "9"], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"start-up worker failed:\n{r.stderr[-2000:]}")
    up = json.loads(r.stdout.strip().splitlines()[-1])
    rows.append({"vehicles": 0, "large_network": f"netgenerate grid 9x9x100 m, 2 lanes: {up['lane_km']:.1f} lane-km, "
                 f"{up['map_tokens']} map tokens", "startup_s": round(up["startup_s"], 2),
                 "startup_cpu_s": round(up["startup_cpu_s"], 2), "startup_eager_s": round(up["startup_eager_s"], 2),
                 "startup_eager_cpu_s": round(up["startup_eager_cpu_s"], 2), "startup_warm_s": round(up["startup_warm_s"], 2),
                 "startup_warm_cpu_s": round(up["startup_warm_cpu_s"], 2),
                 "startup_peak_rss_added_mib": round(up["peak_rss_mib_after"] - up["peak_rss_mib_before"]),
                 "peak_rss_mib_policy": round(up["peak_rss_mib_after"])})
    return {
        "title": "SUMO drop-in controller: simulated s per wall s, policy vs native (motorway_merge, city grid)",
        "rows": rows,
        "notes": [
            f"horizon {horizon:g} s simulated per configuration; each configuration in its own process",
            "shipped r1sim-nano with the drop-in defaults, 2 torch threads; drive commands (default) or position (Krauss "
            "safety filter); off-road and standstill hand-offs disabled; native = SUMO alone, one run per scene",
            "scenes: merge = motorway_merge with ~N cars on 1.5 km of mainline; grid = the 9 x 9 netgenerate city grid "
            "(~46 lane-km, signalised) with ~N cars on random trips (benchmarks/bench_sumo_controller.GridTrips)",
            "targets (issue 20): >= 20 simulated s per wall s at 100 controlled vehicles, >= 5 at 700",
            "last row: building the controller on a ~46 lane-km generated city grid (target <= 2 s, <= 1 GB)",
            "shares: of the policy run's wall time; checks = hand-over, off-road/route checks, SAT, context selection",
        ],
    }


if __name__ == "__main__":
    if len(sys.argv) >= 3 and sys.argv[1] == "--startup":
        print(json.dumps(startup_worker(int(sys.argv[2]))))
    elif len(sys.argv) >= 5 and sys.argv[1] == "--worker":
        print(json.dumps(worker(sys.argv[2], int(sys.argv[3]), float(sys.argv[4]), *sys.argv[5:7])))
    else:
        res = run(quick="--quick" in sys.argv)
        for row in res["rows"]:
            print(row)
