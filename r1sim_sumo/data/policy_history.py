"""Policy-then-SUMO windows: the policy drives, then SUMO takes over and shows how to recover (issue 19, session 17).

Why: a policy trained on SUMO's logs sees only states SUMO's drivers make. Dropped into SUMO it makes its own:
cars settled at 20 m/s on a free 33 m/s motorway, queues behind a merge that discharge slowly
(``scripts/diag_steady_start.py``, ``docs/simulate``). Those states never appear in the log, so nothing teaches it
what to do there (the DAgger argument). Here the policy itself makes them: during recording every vehicle is
driven by the policy through :class:`~r1sim_sumo.sim.sumo_controller.SumoController` (the ``commands`` drive, the
drop-in users run) for a *policy phase*, then :meth:`~r1sim_sumo.sim.sumo_controller.SumoController.pause` hands
them all to SUMO for one window's future (8 s), then the policy drives again. Each window is cut so that its
current index is the hand-over: the 1 s history (two tokens) is the policy's driving, the 8 s future is SUMO's
answer from there. The window's metadata ``label_from_token`` (= 2) tells training to use only the future tokens as
labels (:mod:`r1sim_sumo.tokens.compact` stores it per scene), so the policy is never trained on its own choices.

Phase lengths are drawn per cycle, uniform in ``policy_s`` [s] (longer phases drift further from the log's states),
from ``numpy.random.default_rng([seed, 0xDA66])``: a (network, seed, checkpoint) run is reproducible up to the
policy's sampling, which is seeded by the run's seed too.

Frames: all poses are SUMO's, recorded by :class:`~r1sim_sumo.data.sumo_reference.TrackRecorder` as for any run.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from r1sim_sumo.scenario import CURRENT_INDEX, N_WINDOW_10HZ
from r1sim_sumo.tokens.constants import CURRENT_POSE

FUTURE_STEPS = N_WINDOW_10HZ - 1 - CURRENT_INDEX  # 10 Hz steps SUMO drives after the hand-over (8 s)
DECISION_STEPS = 5  # the controller decides every 0.5 s
LABEL_FROM_TOKEN = CURRENT_POSE  # tokens before the hand-over pose are the policy's: not labels


@dataclass
class PolicyHistorySettings:
    """:param checkpoint: the policy that drives the policy phases (``load_policy`` name or checkpoint folder).
    :param policy_s: ``(lo, hi)`` seconds of each policy phase (>= the 1.1 s history a window needs).
    :param sampler: the policy's sampler (as the drop-in's ``--sampler``).
    :param drive: ``commands`` or ``position`` (as the drop-in's ``--drive``)."""

    checkpoint: str
    policy_s: tuple[float, float] = (4.0, 16.0)
    sampler: str = "topk:5"
    drive: str = "commands"

    def __post_init__(self) -> None:
        lo, hi = (float(v) for v in self.policy_s)
        min_s = (CURRENT_INDEX + 1) * 0.1
        if not min_s <= lo <= hi:
            raise ValueError(f"policy_history_s: need {min_s:.1f} <= lo <= hi [s] (a window's history is policy-driven), "
                             f"got {self.policy_s}")
        self.policy_s = (lo, hi)
        if self.drive not in ("commands", "position"):
            raise ValueError(f"policy_history_drive: use 'commands' or 'position', got {self.drive!r}")


def phase_schedule(n_rec: int, settings: PolicyHistorySettings, seed: int) -> tuple[list[int], list[int]]:
    """``(handovers, starts)``: the recording steps (0.1 s) at which SUMO takes over from the policy, and the window
    start of each (hand-over - :data:`CURRENT_INDEX`). The policy drives from step 0 (and again from each
    ``handover + FUTURE_STEPS``) for a drawn phase length, rounded up to whole 0.5 s decisions; a window is kept only
    if its future ends inside the recording."""
    rng = np.random.default_rng([int(seed), 0xDA66])
    lo, hi = settings.policy_s
    handovers, starts, t = [], [], 0
    while True:
        steps = int(np.ceil(rng.uniform(lo, hi) * 10 / DECISION_STEPS)) * DECISION_STEPS
        h = t + steps
        if h + FUTURE_STEPS >= n_rec:
            return handovers, starts
        handovers.append(h)
        starts.append(h - CURRENT_INDEX)
        t = h + FUTURE_STEPS


@dataclass
class PolicyPhases:
    """Drive a libsumo run in alternating policy / SUMO phases. Create after ``libsumo.start``; call
    :meth:`after_step` right after every ``simulationStep`` of the recorded part (``i`` = recording step just made)."""

    settings: PolicyHistorySettings
    seed: int
    n_rec: int
    net_file: str
    handovers: list[int] = field(init=False)
    starts: list[int] = field(init=False)
    controller: object = field(init=False, default=None, repr=False)

    def __post_init__(self) -> None:
        self.handovers, self.starts = phase_schedule(self.n_rec, self.settings, self.seed)
        self._resume_at = {h + FUTURE_STEPS for h in self.handovers}
        self._pause_at = set(self.handovers)

    def start(self, conn) -> None:
        """Attach the controller (loads the policy once; one thread is the caller's business)."""
        from r1sim_sumo.model.checkpoint import load_policy
        from r1sim_sumo.sim.sumo_controller import SumoController

        policy = load_policy(self.settings.checkpoint)
        self.controller = SumoController(conn, policy, net_file=self.net_file, control="all",
                                         sampler=self.settings.sampler, seed=int(self.seed), drive=self.settings.drive,
                                         map_cache_dir=None, lane_changes="policy", merge_cooperation=False,
                                         lane_change_gate="off", speed_carry="off", junction_turns="policy",
                                         junction_crossings="policy", along_lane=False)  # the recipe's windows as
        # built (session 56-58; the drop-in's later defaults, SUMO driving junction turns (session 60) and crossings
        # (63-64), the along-lane rules (65), are not in them)

    def after_step(self, i: int) -> None:
        """The controller's step for recording step ``i`` (the state SUMO just reached is recorded as step ``i + 1``
        by the caller's next read), then the phase switch: SUMO takes over *before* step ``handover`` is simulated."""
        c = self.controller
        c.step()
        nxt = i + 1
        if nxt in self._pause_at:
            c.pause()
        elif nxt in self._resume_at:
            c.resume()

    def stats(self) -> dict:
        s = self.controller.stats if self.controller is not None else None
        out = {"policy_history_windows": len(self.starts)}
        if s is not None:
            out.update({"policy_history_collisions": int(s.collisions_any),
                        "policy_history_controlled_total": int(s.controlled_total),
                        "policy_history_vkm_controlled": round(float(s.vkm_controlled), 3)})
        return out
