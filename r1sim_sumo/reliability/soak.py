"""Soak run: a long SUMO simulation with the learned controller driving every vehicle, watched for leaks and losses.

``python -m r1sim_sumo.reliability soak --sim-seconds 3600 --out docs/reliability/soak`` (or ``scripts/soak.py``):

* demand: the bundled network's route file with every ``<flow>``'s ``end`` moved to the soak's end, so traffic
  keeps arriving for the whole run (the bundled demand stops at 900 s); written to a temporary folder;
* SUMO through libsumo, started as ``r1sim simulate`` starts it (0.1 s steps, ``--time-to-teleport -1``...),
  :class:`~r1sim_sumo.sim.sumo_controller.SumoController` with the given checkpoint (default: the shipped one);
* every ``sample_every_s`` simulated seconds a row of ``soak.csv``: process RSS [MB], vehicles running /
  departed / arrived / removed (controller counters), SUMO's own departed/arrived totals, controlled now, stuck;
* population: SUMO's ``--max-num-vehicles max_running`` caps the vehicles in the network (insertion waits), so
  that a run whose traffic slows down still reaches a level population and memory can be judged at it;
* memory: at each sample the raw RSS, then (glibc) ``malloc_trim(0)`` hands freed heap pages back to the system and
  the RSS is read again (``rss_live_mb``: memory in use, without the allocator's cached free pages, which step up
  whenever a decision sees a larger batch than before), and ``sys.getallocatedblocks()`` counts live Python objects.
  Over the second half the live RSS is regressed on simulated time *and* the number of running vehicles; the time
  coefficient (MB per simulated hour at a fixed population) must stay within ``MAX_LEAK_MB_PER_H`` (``memory_flat``);
  the running-vehicle coefficient (MB per vehicle) is reported;
* balance: ``departed == arrived + removed + running`` (controller) and controller departed == SUMO departed;
* stuck vehicles: a controlled vehicle that has moved less than ``0.5 m`` per second for more than
  ``stuck_after_s`` seconds while it has no leader within 30 m and no red/yellow signal within 50 m ahead;
* outputs: ``soak.csv``, ``soak_rss.png`` (RSS and running vehicles over simulated time), ``soak.json`` (summary:
  RSS start/end/max, RSS slope [MB per simulated hour] over the second half, wall time, balance, stuck ids).
"""

from __future__ import annotations

import csv
import ctypes
import json
import os
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo._memory import rss_mb
from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.resources import network_files, network_path
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

MAX_LEAK_MB_PER_H = 10.0  # [MB per simulated hour] at a fixed population: more is a leak
MIN_LEAK_WINDOW_S = 1800.0  # [s] simulated: shorter soaks do not judge memory (warm-up dominates)

FIELDS = ["sim_s", "wall_s", "rss_mb", "rss_live_mb", "py_blocks", "running", "departed", "arrived", "removed", "sumo_departed", "sumo_arrived",
          "controlled_now", "controlled_total", "balanced", "stuck_now", "collisions_any", "policy_errors"]


@dataclass
class SoakSummary:
    sim_seconds: float
    wall_s: float
    sim_s_per_wall_s: float
    rss_start_mb: float
    rss_end_mb: float
    rss_max_mb: float
    rss_slope_mb_per_sim_h: float  # least-squares slope over the second half of the run
    rss_leak_mb_per_sim_h: float  # live-RSS time coefficient over the second half, running vehicles held fixed
    rss_per_vehicle_mb: float  # running-vehicle coefficient of the same regression
    rss_live_start_mb: float  # after malloc_trim
    rss_live_end_mb: float
    py_blocks_start: int  # sys.getallocatedblocks(): live Python objects
    py_blocks_end: int
    max_running: int | None
    departed: int
    arrived: int
    removed: int
    running: int
    sumo_departed: int
    balanced_every_sample: bool
    matches_sumo_departed: bool
    stuck_vehicles: list[str] = field(default_factory=list)
    handbacks: dict = field(default_factory=dict)
    collisions_any: int = 0
    policy_errors: int = 0
    checkpoint: str = ""
    network: str = ""

    @property
    def memory_judged(self) -> bool:
        """Runs shorter than MIN_LEAK_WINDOW_S are too short to tell a leak from warm-up."""
        return self.sim_seconds >= MIN_LEAK_WINDOW_S

    @property
    def memory_flat(self) -> bool | None:
        return abs(self.rss_leak_mb_per_sim_h) <= MAX_LEAK_MB_PER_H if self.memory_judged else None

    @property
    def passed(self) -> bool:
        return (self.balanced_every_sample and self.matches_sumo_departed and not self.stuck_vehicles and self.policy_errors == 0
                and self.memory_flat is not False)


def trim_heap() -> bool:
    """Return freed heap pages to the system (glibc ``malloc_trim``); False where it is not available."""
    try:
        return bool(ctypes.CDLL("libc.so.6").malloc_trim(0))
    except (OSError, AttributeError):
        return False


def continuous_demand(network: str, end_s: float, folder: Path) -> Path:
    """A ``.sumocfg`` in ``folder`` running bundled ``network`` with every flow of its demand lasting until ``end_s``."""
    files = network_files(network)
    routes = sorted(network_path(network).glob("*.rou.xml"))
    if not routes:
        raise FileNotFoundError(f"network {network!r} has no .rou.xml demand to extend")
    tree = ET.parse(routes[0])
    n_flows = 0
    for fl in tree.getroot().iter("flow"):
        fl.set("end", f"{float(end_s) + 10.0:g}")
        n_flows += 1
    if n_flows == 0:
        raise ValueError(f"{routes[0]}: no <flow> elements: demand cannot be made continuous")
    folder.mkdir(parents=True, exist_ok=True)
    rou = folder / "continuous.rou.xml"
    tree.write(rou, encoding="unicode")
    cfg = folder / "soak.sumocfg"
    cfg.write_text(f'<configuration>\n  <input>\n    <net-file value="{files["net"].resolve()}"/>\n'
                   f'    <route-files value="{rou.resolve()}"/>\n  </input>\n</configuration>\n')
    return cfg


class StuckWatch:
    """Per-second check of controlled vehicles for standing still without a reason (see module docstring)."""

    def __init__(self, stuck_after_s: float, min_move_m: float = 0.5):
        self.after_s = float(stuck_after_s)
        self.min_move_m = float(min_move_m)
        self.last: dict[str, tuple[float, float]] = {}
        self.still_s: dict[str, float] = {}
        self.stuck: set[str] = set()

    def _excused(self, conn, vid: str) -> bool:
        try:
            lead = conn.vehicle.getLeader(vid, 30.0)
            if lead and lead[0]:
                return True
            for _tls, _idx, dist, state in conn.vehicle.getNextTLS(vid):
                if dist < 50.0 and state in "rRyYu":
                    return True
        except Exception:  # noqa: BLE001 - vehicle just left
            return True
        return False

    def check(self, conn, controlled: list[str], dt_s: float) -> int:
        """Update with the current positions (call every ``dt_s`` simulated seconds); returns how many are stuck now."""
        now = 0
        seen = set()
        for vid in controlled:
            seen.add(vid)
            x, y = conn.vehicle.getPosition(vid)
            px, py = self.last.get(vid, (x + 1e9, y))
            self.last[vid] = (x, y)
            if np.hypot(x - px, y - py) < self.min_move_m * dt_s and not self._excused(conn, vid):
                self.still_s[vid] = self.still_s.get(vid, 0.0) + dt_s
            else:
                self.still_s[vid] = 0.0
            if self.still_s[vid] > self.after_s:
                self.stuck.add(vid)
                now += 1
        for vid in list(self.last):
            if vid not in seen:
                self.last.pop(vid)
                self.still_s.pop(vid, None)
        return now


def run_soak(sim_seconds: float, out: str | os.PathLike, network: str = "motorway_merge", checkpoint: str | None = None,
             sample_every_s: float = 10.0, stuck_after_s: float = 60.0, seed: int = 0, sampler: str = "topk:5",
             progress: bool = False, max_running: int | None = 150) -> SoakSummary:
    """Run the soak (see module docstring); writes ``soak.csv``, ``soak_rss.png``, ``soak.json`` into ``out``."""
    import libsumo

    ensure_sumo_home()
    torch.set_num_threads(1)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    policy = r1sim_sumo.load_policy(checkpoint)
    n = int(round(sim_seconds / 0.1))
    every = max(1, int(round(sample_every_s / 0.1)))
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        cfg = continuous_demand(network, sim_seconds, Path(tmp))
        cmd = sumo_command(seed, sumocfg=cfg, end_s=sim_seconds + 1.0)
        if max_running:
            cmd += ["--max-num-vehicles", str(int(max_running))]
        libsumo.start(cmd)
        try:
            ctrl = SumoController(libsumo, policy, control="all", sampler=sampler, seed=seed)
            watch = StuckWatch(stuck_after_s)
            sumo_dep = sumo_arr = 0
            t0 = time.perf_counter()
            stuck_now = 0
            for k in range(1, n + 1):
                libsumo.simulationStep()
                ctrl.step()
                sumo_dep += libsumo.simulation.getDepartedNumber()
                sumo_arr += libsumo.simulation.getArrivedNumber()
                if k % 10 == 0:
                    stuck_now = watch.check(libsumo, ctrl.controlled_ids(), 1.0)
                if k % every == 0 or k == n:
                    s = ctrl.stats
                    rows.append({"sim_s": round(k * 0.1, 1), "wall_s": round(time.perf_counter() - t0, 2), "rss_mb": round(rss_mb(), 1),
                                 "rss_live_mb": round(rss_mb(), 1) if trim_heap() else round(rss_mb(), 1),
                                 "py_blocks": sys.getallocatedblocks(),
                                 "running": s.running, "departed": s.departed, "arrived": s.arrived, "removed": s.removed,
                                 "sumo_departed": sumo_dep, "sumo_arrived": sumo_arr, "controlled_now": s.controlled_now,
                                 "controlled_total": s.controlled_total,
                                 "balanced": s.departed == s.arrived + s.removed + s.running, "stuck_now": stuck_now,
                                 "collisions_any": s.collisions_any, "policy_errors": s.policy_errors})
                    if progress:
                        print(f"[soak] {rows[-1]}", flush=True)
            wall = time.perf_counter() - t0
        finally:
            settle_remote_control(libsumo)  # the controller's last moves (see r1sim_sumo.sumo_launch)
            libsumo.close()
    with open(out / "soak.csv", "w", newline="") as f:
        w = csv.DictWriter(f, FIELDS)
        w.writeheader()
        w.writerows(rows)
    s = ctrl.stats
    summary = SoakSummary(
        sim_seconds=n * 0.1, wall_s=round(wall, 1), sim_s_per_wall_s=round(n * 0.1 / max(wall, 1e-9), 2),
        rss_start_mb=rows[0]["rss_mb"], rss_end_mb=rows[-1]["rss_mb"], rss_max_mb=max(r["rss_mb"] for r in rows),
        rss_slope_mb_per_sim_h=round(rss_slope(rows), 2), rss_leak_mb_per_sim_h=round(rss_leak(rows)[0], 2),
        rss_per_vehicle_mb=round(rss_leak(rows)[1], 4), max_running=max_running,
        rss_live_start_mb=rows[0]["rss_live_mb"], rss_live_end_mb=rows[-1]["rss_live_mb"],
        py_blocks_start=rows[0]["py_blocks"], py_blocks_end=rows[-1]["py_blocks"], departed=s.departed, arrived=s.arrived, removed=s.removed,
        running=s.running, sumo_departed=sumo_dep, balanced_every_sample=all(r["balanced"] for r in rows),
        matches_sumo_departed=s.departed == sumo_dep, stuck_vehicles=sorted(watch.stuck), handbacks=dict(s.handbacks),
        collisions_any=s.collisions_any, policy_errors=s.policy_errors,
        checkpoint=str(checkpoint or "r1sim-nano (shipped)"), network=network,
    )
    (out / "soak.json").write_text(json.dumps({**asdict(summary), "memory_judged": summary.memory_judged, "memory_flat": summary.memory_flat, "passed": summary.passed},
                                              indent=1))
    plot_rss(rows, out / "soak_rss.png")
    return summary


def rss_slope(rows: list[dict], key: str = "rss_mb") -> float:
    """Least-squares RSS slope [MB per simulated hour] over the second half of the samples (after warm-up)."""
    half = rows[len(rows) // 2:]
    if len(half) < 2:
        return 0.0
    t = np.array([r["sim_s"] for r in half], float) / 3600.0
    m = np.array([r.get(key, r["rss_mb"]) for r in half], float)
    return float(np.polyfit(t, m, 1)[0])


def rss_leak(rows: list[dict], key: str = "rss_live_mb") -> tuple[float, float]:
    """Over the second half: RSS ~ a + b * sim_hours + c * running; returns (b [MB per simulated hour at a fixed
    population], c [MB per running vehicle]). Without variation in ``running`` it is :func:`rss_slope`, c = 0."""
    half = rows[len(rows) // 2:]
    if len(half) < 3:
        return 0.0, 0.0
    t = np.array([r["sim_s"] for r in half], float) / 3600.0
    n = np.array([r["running"] for r in half], float)
    m = np.array([r.get(key, r["rss_mb"]) for r in half], float)
    if np.ptp(n) == 0:
        return rss_slope(rows, key), 0.0
    X = np.stack([np.ones_like(t), t, n], 1)
    coef, *_ = np.linalg.lstsq(X, m, rcond=None)
    return float(coef[1]), float(coef[2])


def plot_rss(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [r["sim_s"] for r in rows]
    fig, ax = plt.subplots(figsize=(7, 3.2))
    ax.plot(t, [r["rss_mb"] for r in rows], color="tab:blue", label="RSS [MB]")
    if "rss_live_mb" in rows[0]:
        ax.plot(t, [r["rss_live_mb"] for r in rows], color="tab:blue", ls="--", label="RSS after malloc_trim [MB]")
        ax.legend(loc="lower right", fontsize=8)
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("process RSS [MB]", color="tab:blue")
    ax2 = ax.twinx()
    ax2.plot(t, [r["running"] for r in rows], color="tab:orange", alpha=0.7, label="vehicles running")
    ax2.set_ylabel("vehicles running", color="tab:orange")
    ax.set_title("soak: memory and traffic over time")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
