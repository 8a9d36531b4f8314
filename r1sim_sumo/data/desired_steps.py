"""Random steps of SUMO drivers' desired speed while reference data is recorded, so the data shows a driver that has
cruised *steadily below* its desired speed on a free road and now speeds up to it.

Why: in Krauss/IDM traffic a driver below its desired speed with a free road accelerates at once, so the recorded
data never holds the state "steady past, free road, desired speed well above" (a car cruises at its desired speed or
is held by a leader). A policy trained on it copies its steady past there: the shipped nano, alone on a free lane at a
steady 22-25 m/s with 33.3 m/s desired, stays at 24.5 m/s (``python -m r1sim_sumo.evaluate_free_road r1sim-nano
--desired --accel``: +0.18 m/s^2 from a steady 25 m/s with 10 m/s to go, SUMO's drivers ~2). The same state is what a
policy vehicle in the drop-in meets after every slow-down.

One event, for a vehicle driving faster than :data:`MIN_SPEED_MPS` and not already in an event:

1. its speedFactor becomes ``U(factor) x`` its own (``vehicle.setSpeedFactor``): SUMO's driver now wants a lower
   speed, slows to it (SUMO's car-following model, bounded by the type's deceleration) and cruises there;
2. after ``U(hold_s)`` seconds its own speedFactor comes back, and SUMO's model speeds it up to its desired speed.
   With ``restore_at`` (the steps where recorded windows have their current index) the low phase is stretched to end
   ``U{0..LEAD_MAX_STEPS}`` steps before the next such step, so that each event is seen by a window right at its
   step up (windows every 2 s would otherwise catch the first 0.5 s of a speed-up about once in four events).

The desired speed each window records (:func:`~r1sim_sumo.adapters.sumo_state.read_desired_speeds`, lane limit x
speedFactor) follows both steps, so every label is SUMO's driver doing what its recorded desired speed asks: the
windows just after a step up hold a steady past, a desired speed above it and the speed-up. All motion stays SUMO's
car-following model with legal parameters: no speed or position is set. Events start independently per vehicle and
step with probability ``rate_per_vehicle_hour * dt / 3600``; draws come from ``numpy.random.default_rng([seed,
0xDE51])``, so a (network, seed) run is reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from r1sim_sumo.data.slowdowns import draw_vehicles

MIN_SPEED_MPS = 5.0  # [m/s] slower vehicles (queues, junctions) are left alone
LEAD_MAX_STEPS = 4  # [0.1 s steps] with restore_at: the step up comes 0..this many steps before a window's current index


@dataclass
class DesiredStepSettings:
    """:param rate_per_vehicle_hour: expected events per vehicle and hour of driving (0 = off).
    :param factor: ``(lo, hi)`` multiplier of the driver's own speedFactor during the low phase (0 < lo <= hi < 1).
    :param hold_s: ``(lo, hi)`` seconds of the low phase before the driver's own speedFactor comes back."""

    rate_per_vehicle_hour: float = 0.0
    factor: tuple[float, float] = (0.55, 0.9)
    hold_s: tuple[float, float] = (4.0, 12.0)

    def __post_init__(self) -> None:
        if self.rate_per_vehicle_hour < 0:
            raise ValueError(f"desired_steps_per_vehicle_hour: must be >= 0, got {self.rate_per_vehicle_hour}")
        lo, hi = self.factor
        if not 0 < lo <= hi < 1:
            raise ValueError(f"desired_step_factor: need 0 < lo <= hi < 1, got ({lo}, {hi})")
        lo, hi = self.hold_s
        if not 0 < lo <= hi:
            raise ValueError(f"desired_step_hold_s: need 0 < lo <= hi [s], got ({lo}, {hi})")
        self.factor = (float(self.factor[0]), float(self.factor[1]))
        self.hold_s = (float(self.hold_s[0]), float(self.hold_s[1]))


@dataclass
class DesiredStepInjector:
    """Call :meth:`before_step` once before every ``simulationStep`` of a libsumo/TraCI run.

    :param step_s: the simulation step length [s].
    :param restore_at: optional sorted steps (counted in :meth:`before_step` calls from 0) at which recorded windows
        have their current index; the low phases then end just before one of them (module doc)."""

    settings: DesiredStepSettings
    seed: int
    step_s: float
    restore_at: np.ndarray | None = None
    events: int = 0
    _rng: np.random.Generator = field(init=False, repr=False)
    _ends: dict[int, list[tuple[str, float]]] = field(init=False, repr=False, default_factory=dict)
    _busy: set[str] = field(init=False, repr=False, default_factory=set)
    _k: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng([int(self.seed), 0xDE51])

    @property
    def active(self) -> bool:
        """Whether new events start (events under way always end, also after the rate is set to 0)."""
        return self.settings.rate_per_vehicle_hour > 0 or bool(self._ends)

    def before_step(self, sumo) -> None:
        """Give back the own speedFactor of drivers whose low phase is over, then start new events (``sumo``: libsumo
        or traci)."""
        k = self._k
        self._k += 1
        ends = self._ends.pop(k, ())
        if ends:
            present = set(sumo.vehicle.getIDList())
            for vid, own in ends:
                self._busy.discard(vid)
                if vid in present:
                    sumo.vehicle.setSpeedFactor(vid, own)
        s = self.settings
        for vid in draw_vehicles(sumo, self._rng, s.rate_per_vehicle_hour * self.step_s / 3600.0):
            m, hold = self._rng.uniform(*s.factor), self._rng.uniform(*s.hold_s)
            if vid in self._busy or sumo.vehicle.getSpeed(vid) < MIN_SPEED_MPS:
                continue
            end = self._end_step(k, hold)
            if end is None:
                continue
            own = float(sumo.vehicle.getSpeedFactor(vid))
            sumo.vehicle.setSpeedFactor(vid, own * m)
            self._busy.add(vid)
            self._ends.setdefault(end, []).append((vid, own))
            self.events += 1

    def _end_step(self, k: int, hold_s: float) -> int | None:
        """The step whose :meth:`before_step` gives the own speedFactor back: ``hold_s`` after ``k``, or with
        ``restore_at`` 0..LEAD_MAX_STEPS steps before the first window step at least that far on (``None``: none left,
        no event)."""
        end = k + max(1, int(round(hold_s / self.step_s)))
        if self.restore_at is None:
            return end
        lead = int(self._rng.integers(0, LEAD_MAX_STEPS + 1))
        j = int(np.searchsorted(self.restore_at, end + lead))
        return None if j >= len(self.restore_at) else int(self.restore_at[j]) - lead
