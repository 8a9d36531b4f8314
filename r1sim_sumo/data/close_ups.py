"""Random close-ups of SUMO vehicles while reference data is recorded, so the data shows followers closing up on
their leader and braking to reopen a gap that has become too short.

Why: in Krauss/IDM traffic every follower keeps its type's time headway (``tau``, about 1 s) at all times, so the
default recipe never shows a vehicle that is *too close* to a slower leader, nor one far behind an accelerating
leader that closes up at full acceleration. A policy trained on it holds its own speed behind a slower leader
(``scripts/diag_follow_leader.py``: the shipped nano keeps 31-32 m/s 8 m behind a 20 m/s leader) and lets gaps
grow behind a leader that speeds up, so a merge in the drop-in leaves slow platoons behind it (``docs/simulate``).

One event, for a vehicle driving faster than :data:`MIN_SPEED_MPS` with a leader within :data:`MAX_GAP_M`:

1. the driver becomes a tailgater: its headway ``tau`` [s] becomes ``U(tau_s)`` and its ``minGap`` [m]
   ``U(min_gap_m)`` (``vehicle.setTau`` / ``vehicle.setMinGap``), so SUMO's own car-following model closes the gap
   at up to the type's acceleration, as a hurried driver does;
2. after ``U(hold_s)`` seconds the driver's own ``tau`` and ``minGap`` come back: it is now closer than it wants to
   be and brakes (again SUMO's model, bounded by the type's deceleration) until its gap is back.

All motion stays SUMO's car-following model with legal parameters: no position or speed is set, nothing collides.
Events start independently per vehicle and step with probability ``rate_per_vehicle_hour * dt / 3600``; a vehicle
already in an event is not picked again. Draws come from ``numpy.random.default_rng([seed, 0xC105E])``, so a
(network, seed) run is reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from r1sim_sumo.data.slowdowns import draw_vehicles

MIN_SPEED_MPS = 3.0  # [m/s] slower vehicles are left alone (queues at lights need no tailgaters)
MAX_GAP_M = 120.0  # [m] a vehicle with no leader within this gap (front bumper to leader's rear) is left alone


@dataclass
class CloseUpSettings:
    """:param rate_per_vehicle_hour: expected close-up events per vehicle and hour of driving (0 = off).
    :param tau_s: ``(lo, hi)`` headway [s] of the tailgating phase (SUMO's default is 1 s; keep ``lo`` >= 0.2).
    :param min_gap_m: ``(lo, hi)`` standstill gap [m] of the tailgating phase (SUMO's default 2.5 m).
    :param hold_s: ``(lo, hi)`` seconds of tailgating before the driver's own headway comes back."""

    rate_per_vehicle_hour: float = 0.0
    tau_s: tuple[float, float] = (0.25, 0.5)
    min_gap_m: tuple[float, float] = (0.5, 1.5)
    hold_s: tuple[float, float] = (4.0, 12.0)

    def __post_init__(self) -> None:
        if self.rate_per_vehicle_hour < 0:
            raise ValueError(f"close_ups_per_vehicle_hour: must be >= 0, got {self.rate_per_vehicle_hour}")
        for name, (lo, hi), low in (("tau_s", self.tau_s, 0.1), ("min_gap_m", self.min_gap_m, 0.0),
                                    ("hold_s", self.hold_s, 0.0)):
            if not low <= lo <= hi:
                raise ValueError(f"close-up {name}: need {low} <= lo <= hi, got ({lo}, {hi})")


@dataclass
class CloseUpInjector:
    """Call :meth:`before_step` once before every ``simulationStep`` of a libsumo/TraCI run.

    :param step_s: the simulation step length [s]."""

    settings: CloseUpSettings
    seed: int
    step_s: float
    events: int = 0
    _rng: np.random.Generator = field(init=False, repr=False)
    _ends: dict[int, list[tuple[str, float, float]]] = field(init=False, repr=False, default_factory=dict)
    _busy: set[str] = field(init=False, repr=False, default_factory=set)
    _k: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng([int(self.seed), 0xC105E])

    @property
    def active(self) -> bool:
        """Whether new events start (events under way always end, also after the rate is set to 0)."""
        return self.settings.rate_per_vehicle_hour > 0 or bool(self._ends)

    def before_step(self, sumo) -> None:
        """End the events whose hold is over, then start new ones (``sumo``: libsumo or traci)."""
        k = self._k
        self._k += 1
        ends = self._ends.pop(k, ())
        if ends:
            present = set(sumo.vehicle.getIDList())
            for vid, tau, gap in ends:
                self._busy.discard(vid)
                if vid in present:
                    sumo.vehicle.setTau(vid, tau)
                    sumo.vehicle.setMinGap(vid, gap)
        s = self.settings
        for vid in draw_vehicles(sumo, self._rng, s.rate_per_vehicle_hour * self.step_s / 3600.0):
            tau, gap, hold = self._rng.uniform(*s.tau_s), self._rng.uniform(*s.min_gap_m), self._rng.uniform(*s.hold_s)
            if vid in self._busy or sumo.vehicle.getSpeed(vid) < MIN_SPEED_MPS:
                continue
            leader = sumo.vehicle.getLeader(vid, MAX_GAP_M)
            if not leader or not leader[0]:
                continue
            own = (sumo.vehicle.getTau(vid), sumo.vehicle.getMinGap(vid))
            sumo.vehicle.setTau(vid, tau)
            sumo.vehicle.setMinGap(vid, gap)
            self._busy.add(vid)
            self._ends.setdefault(k + max(1, int(round(hold / self.step_s))), []).append((vid, *own))
            self.events += 1
