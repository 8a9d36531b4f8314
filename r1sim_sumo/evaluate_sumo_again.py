"""The "SUMO again" baseline: the reference simulator rerun from the scenario's start with other random seeds.

A SUMO reference scenario generated with ``save_states`` carries a SUMO state saved at its current index (10 Hz state
10; ``metadata["state_file"]``, relative to the dataset folder). Rollout ``i`` restores it in a SUMO started with
``--seed <seed_i>`` and lets SUMO's own models drive for the 80 future steps (8 s at 0.1 s). The saved state holds
the generator's RNG state as a number of draws from the *generation* seed's stream; restoring it under another
``--seed`` replays that many draws of a different stream, so driver imperfection (Krauss ``sigma``), departure speeds
and lane-change randomness differ from the log while positions, speeds, routes and signal phases start identical
The seeds skip the scenario's generation seed (which would replay the log). Measured on ``motorway_merge`` /
``urban_intersection`` (``data/generated/states_small``): the agents' futures under another seed stay within ~2-3 cm
of the log on average (median final-step error ~1 cm, a few vehicles metres apart): on free-flowing roads Krauss
dawdling is re-corrected every 0.1 s step and IDM drivers have no randomness, so by the seed alone SUMO is nearly
deterministic over 8 s. ``redraw_speed_factor=True`` also redraws every vehicle's desired-speed factor from its
vType's distribution (another population of drivers), which spreads the futures by metres.

The scenario's agents are read back every step (box centre, yaw, internal frame via
:func:`~r1sim_sumo.adapters.sumo_state.read_vehicle_states`); an agent SUMO no longer has (arrived) is invalid from
then on. The result is a :class:`~r1sim_sumo.metrics.types.SimTrajectories` ``[N, A, 80]`` in the scenario's agent
order, scored by :func:`~r1sim_sumo.metrics.realism.compute_realism` like any policy: an upper-reference baseline of
how close *another run of the same simulator* gets to the log (below log replay, above a learned policy when the
policy is worse than SUMO at imitating SUMO).

libsumo holds one simulation per process: this uses (and leaves started) the process's session of
:func:`r1sim_sumo.sumo_launch.sumo_start`; call :func:`~r1sim_sumo.sumo_launch.sumo_close` when done.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from r1sim_sumo.adapters.sumo_state import read_vehicle_states
from r1sim_sumo.data.sumo_reference import scenario_sumo_files, sumo_vehicle_id
from r1sim_sumo.metrics.types import SimTrajectories
from r1sim_sumo.scenario import N_FUTURE_10HZ, Scenario
from r1sim_sumo.sumo_launch import sumo_start

SEED_BASE = 1000  # seeds SEED_BASE, SEED_BASE + 1, ... (skipping the generation seed)


def again_seeds(scenario: Scenario, num_rollouts: int, base: int = SEED_BASE) -> list[int]:
    """``num_rollouts`` SUMO seeds different from the scenario's generation seed (``metadata["seed"]``)."""
    gen = scenario.metadata.get("seed")
    out, s = [], int(base)
    while len(out) < num_rollouts:
        if gen is None or s != int(gen):
            out.append(s)
        s += 1
    return out


def sumo_again_sim(scenario: Scenario, root: str | os.PathLike, num_rollouts: int = 8, seed_base: int = SEED_BASE,
                   time_to_teleport_s: float = 300.0, redraw_speed_factor: bool = False) -> SimTrajectories:
    """Rerun SUMO from the scenario's saved state ``num_rollouts`` times (one ``--seed`` each); ``[N, A, T]`` futures.

    :param root: the dataset folder the scenario's ``state_file`` is relative to.
    :param time_to_teleport_s: SUMO ``--time-to-teleport`` as in generation (``SumoGenConfig.time_to_teleport_s``).
    :param redraw_speed_factor: also give every vehicle present a new desired-speed factor drawn (numpy, seeded by
        the rollout's seed) from its vType's ``speedFactor`` mean and deviation, clipped to [0.2, 2]: "other drivers"
        rather than only other dawdling noise. The seed alone changes 8 s futures by centimetres on free-flowing
        roads (Krauss dawdling re-accelerates each step; IDM has no randomness), see the module doc.
    """

    net, state = scenario_sumo_files(scenario, root, where=f"{root} scenario {scenario.metadata.get('window_index', '?')}")
    a = scenario.agents
    T = min(N_FUTURE_10HZ, scenario.num_steps - scenario.current_index - 1)
    ids = [sumo_vehicle_id(v) for v in np.asarray(a.ids).tolist()]
    now_ok = np.asarray(a.valid[:, scenario.current_index], bool)  # [A]
    A, N = len(ids), int(num_rollouts)
    x, y, yaw = np.zeros((N, A, T)), np.zeros((N, A, T)), np.zeros((N, A, T))
    valid = np.zeros((N, A, T), bool)
    for r, seed in enumerate(again_seeds(scenario, N, seed_base)):
        conn = sumo_start(net, seed, time_to_teleport_s, state_file=state)  # a fresh load: see sumo_start
        if redraw_speed_factor:
            rng = np.random.default_rng(seed)
            for vid in conn.vehicle.getIDList():
                tid = conn.vehicle.getTypeID(vid)
                mean, dev = conn.vehicletype.getSpeedFactor(tid), conn.vehicletype.getSpeedDeviation(tid)
                conn.vehicle.setSpeedFactor(vid, float(np.clip(rng.normal(mean, dev), 0.2, 2.0)))
        for t in range(T):
            conn.simulationStep()
            present = set(conn.vehicle.getIDList())
            rows = [i for i in range(A) if now_ok[i] and ids[i] in present]
            if not rows:
                continue
            st = read_vehicle_states(conn, [ids[i] for i in rows])
            x[r, rows, t], y[r, rows, t], yaw[r, rows, t] = st.x_m, st.y_m, st.yaw_rad
            valid[r, rows, t] = True
    return SimTrajectories(x_m=x, y_m=y, yaw_rad=yaw, valid=valid)


def has_states(scenarios, root: str | os.PathLike | None) -> bool:
    """Whether every scenario carries a state file that exists under ``root``."""
    if root is None:
        return False
    return all((Path(root) / str(scenarios[i].metadata.get("state_file", "\0"))).exists() for i in range(len(scenarios)))
