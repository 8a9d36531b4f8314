"""Random slow-downs of SUMO vehicles while reference data is recorded, so the data holds recoveries.

Why: in the bundled demand every vehicle enters at ``departSpeed="max"`` and Krauss/IDM traffic rarely slows on a
motorway, so the default recipe almost never shows a vehicle *speeding back up* on a free road. A policy trained on
it learns that slow stays slow (the free-road probe, :mod:`r1sim_sumo.evaluate_free_road`). A slow-down here is what
a driver does for a phantom obstacle: brake, hold the low speed for a moment, then let SUMO's own car-following model
take over again, which accelerates back to the desired speed and makes the followers brake and recover too
(stop-and-go waves on dense roads).

One event, for a vehicle driving faster than ``MIN_SPEED_MPS``:

1. brake to ``target = U(0, max_target_fraction) * v`` [m/s] at ``U(decel_mps2)`` [m/s^2] (``vehicle.slowDown``,
   which SUMO still bounds by the vehicle type's deceleration and its safe speed);
2. hold ``target`` for ``U(hold_s)`` seconds (a second ``slowDown`` to the same speed);
3. release: SUMO's car-following model drives again (no ``setSpeed`` is left behind).

Events start independently per vehicle and step with probability ``rate_per_vehicle_hour * dt / 3600``; the draws
come from ``numpy.random.default_rng([seed, 0x510D])``, so a (network, seed) run is reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MIN_SPEED_MPS = 5.0  # vehicles slower than this are not slowed further [m/s]


def draw_vehicles(sumo, rng: np.random.Generator, p: float) -> list[str]:
    """The vehicles in which an event starts this step: each present vehicle independently with probability ``p``
    (one binomial draw of the count, then that many distinct vehicles), in draw order."""
    n = sumo.vehicle.getIDCount()
    m = int(rng.binomial(n, min(p, 1.0))) if n and p > 0 else 0
    if m == 0:
        return []
    ids = sumo.vehicle.getIDList()
    return [ids[int(j)] for j in rng.choice(len(ids), size=min(m, len(ids)), replace=False)]


@dataclass
class SlowdownSettings:
    """:param rate_per_vehicle_hour: expected slow-down events per vehicle and hour of driving (0 = off).
    :param max_target_fraction: the target speed is ``U(0, this) * current speed``.
    :param decel_mps2: ``(lo, hi)`` braking [m/s^2] of the approach to the target.
    :param hold_s: ``(lo, hi)`` seconds spent at the target before SUMO drives again."""

    rate_per_vehicle_hour: float = 0.0
    max_target_fraction: float = 0.6
    decel_mps2: tuple[float, float] = (1.5, 3.5)
    hold_s: tuple[float, float] = (0.0, 4.0)

    def __post_init__(self) -> None:
        if self.rate_per_vehicle_hour < 0:
            raise ValueError(f"slowdowns_per_vehicle_hour: must be >= 0, got {self.rate_per_vehicle_hour}")
        if not 0 < self.max_target_fraction < 1:
            raise ValueError(f"slow-down max_target_fraction: must be in (0, 1), got {self.max_target_fraction}")
        if not 0 < self.decel_mps2[0] <= self.decel_mps2[1]:
            raise ValueError(f"slow-down decel_mps2: need 0 < lo <= hi, got {self.decel_mps2}")
        if not 0 <= self.hold_s[0] <= self.hold_s[1]:
            raise ValueError(f"slowdown_hold_s: need 0 <= lo <= hi [s], got {self.hold_s}")


@dataclass
class SlowdownInjector:
    """Call :meth:`before_step` once before every ``simulationStep`` of a libsumo/TraCI run.

    :param step_s: the simulation step length [s]."""

    settings: SlowdownSettings
    seed: int
    step_s: float
    events: int = 0
    _rng: np.random.Generator = field(init=False, repr=False)
    _holds: dict[int, list[tuple[str, float, float]]] = field(init=False, repr=False, default_factory=dict)
    _k: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng([int(self.seed), 0x510D])
        self._p = self.settings.rate_per_vehicle_hour * self.step_s / 3600.0

    @property
    def active(self) -> bool:
        return self._p > 0

    def before_step(self, sumo) -> None:
        """Start new events and the hold phase of events whose braking ends now (``sumo``: libsumo or traci)."""
        k = self._k
        self._k += 1
        for vid, target, hold in self._holds.pop(k, ()):
            if vid in sumo.vehicle.getIDList() and hold > 0:
                sumo.vehicle.slowDown(vid, target, hold)
        if not self.active:
            return
        s = self.settings
        for vid in draw_vehicles(sumo, self._rng, self._p):
            frac, decel, hold = self._rng.uniform(0, s.max_target_fraction), self._rng.uniform(*s.decel_mps2), self._rng.uniform(*s.hold_s)
            v = sumo.vehicle.getSpeed(vid)
            if v < MIN_SPEED_MPS:
                continue
            target = frac * v
            brake_s = max(self.step_s, (v - target) / decel)
            sumo.vehicle.slowDown(vid, target, brake_s)
            self._holds.setdefault(k + int(round(brake_s / self.step_s)), []).append((vid, target, hold))
            self.events += 1
