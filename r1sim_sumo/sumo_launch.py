"""Starting SUMO: the one place that builds SUMO command lines and (re)loads this process's libsumo.

Every SUMO run of the project (reference-data generation, ``r1sim simulate``, SUMO-in-the-loop training, the
``sumo_again`` evaluation baseline, the ego env, the soak and the examples) gets its command line from
:func:`sumo_command` (or its arguments from :func:`sumo_args`), so all of them run with:

- ``--step-length 0.1`` (:data:`STEP_LENGTH_S` = :data:`r1sim_sumo.scenario.DT_S`: one SUMO step = one 10 Hz state);
- ``--seed <seed>`` (explicit, never SUMO's default);
- :data:`COLLISION_FLAGS`: ``--collision.action warn`` (nothing is removed or teleported; collisions are only
  reported), ``--collision.mingap-factor 0`` (only physical overlaps count, not a violated minGap) and
  ``--collision.check-junctions true`` (overlaps inside junctions count too). With ``warn`` these flags change
  what ``simulation.getCollisions()`` reports, never the dynamics;
- :data:`QUIET_FLAGS`: no step log, no warnings, no duration log.

State loading: ``--load-state FILE`` restores a state saved by ``simulation.saveState`` (with
``--save-state.rng true`` it carries the RNG). SUMO 1.28 restores a saved RNG by *discarding* the saved number of
draws from the generator as it is now (``RandHelper::loadState`` does not reseed), so ``simulation.loadState``
inside a simulation that has already drawn numbers gives other SUMO-driven dynamics (dawdling, insertions) than in
a fresh one. :func:`sumo_start` therefore always (re)loads from scratch when given a state file (~15 ms on the
bundled networks; ``loadState`` alone ~9 ms).

libsumo holds one simulation per process: :func:`sumo_start` / :func:`sumo_close` keep this process's session.

Ending a libsumo simulation: see :func:`settle_remote_control`. Every host of the project that closes or reloads
libsumo after moving vehicles with ``moveToXY`` calls it first.
"""

from __future__ import annotations

import os
from pathlib import Path

from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary
from r1sim_sumo.adapters.sumo_state import clear_static_cache
from r1sim_sumo.scenario import DT_S as STEP_LENGTH_S  # [s] SUMO step = one 10 Hz state

COLLISION_FLAGS = ("--collision.action", "warn", "--collision.mingap-factor", "0", "--collision.check-junctions", "true")
QUIET_FLAGS = ("--no-step-log", "true", "--no-warnings", "true", "--duration-log.disable", "true")


def sumo_args(seed: int, *, sumocfg: str | os.PathLike | None = None, net_file: str | os.PathLike | None = None,
              route_files: str | os.PathLike | None = None, end_s: float | None = None,
              time_to_teleport_s: float | None = -1.0, load_state: str | os.PathLike | None = None,
              save_state_rng: bool = False, fcd_output: str | os.PathLike | None = None,
              error_log: str | os.PathLike | None = None, extra: tuple[str, ...] | list[str] = ()) -> list[str]:
    """SUMO options (no binary) for one run; see the module docstring for the flags every run gets.

    :param seed: SUMO ``--seed``.
    :param sumocfg: a ``.sumocfg`` (``-c``); or ``net_file``: a ``.net.xml`` alone (``-n``, e.g. with ``load_state``).
    :param route_files: ``--route-files`` overriding the config's demand.
    :param end_s: ``--begin 0 --end end_s`` [s simulated]; None: the config's own end.
    :param time_to_teleport_s: ``--time-to-teleport`` [s] (-1: never, policy-driven vehicles must not jump);
        None: SUMO's default (300 s).
    :param load_state: ``--load-state`` file (a state saved by ``simulation.saveState``).
    :param save_state_rng: ``--save-state.rng true --save-state.precision 6`` (states that restore the RNG).
    :param fcd_output: ``--fcd-output`` file with one record per 0.1 s step.
    :param error_log: ``--error-log`` file receiving SUMO's warnings (instead of ``--no-warnings``), for counting them.
    :param extra: further options appended as given (``--scale``, ``--lateral-resolution`` ...).
    """
    if (sumocfg is None) == (net_file is None):
        raise ValueError("sumo_args: pass exactly one of sumocfg (a .sumocfg) or net_file (a .net.xml)")
    args = ["-c", str(sumocfg)] if sumocfg is not None else ["-n", str(net_file)]
    if route_files is not None:
        args += ["--route-files", str(route_files)]
    args += ["--step-length", f"{STEP_LENGTH_S}", "--seed", str(int(seed))]
    if end_s is not None:
        args += ["--begin", "0", "--end", f"{float(end_s)}"]
    quiet = QUIET_FLAGS if error_log is None else ("--no-step-log", "true", "--duration-log.disable", "true",
                                                   "--error-log", str(error_log))
    args += [*quiet, *COLLISION_FLAGS]
    if time_to_teleport_s is not None:
        args += ["--time-to-teleport", f"{float(time_to_teleport_s):g}"]
    if load_state is not None:
        args += ["--load-state", str(load_state)]
    if save_state_rng:
        args += ["--save-state.rng", "true", "--save-state.precision", "6"]
    if fcd_output is not None:
        args += ["--fcd-output", str(fcd_output), "--device.fcd.period", f"{STEP_LENGTH_S}"]
    return [*args, *extra]


def sumo_command(seed: int, *, gui: bool = False, **kwargs) -> list[str]:
    """Full command line (``sumo`` or ``sumo-gui`` binary + :func:`sumo_args`) for ``libsumo.start`` /
    ``traci.start``; ``gui`` also starts the simulation and quits sumo-gui at its end."""
    cmd = [sumo_binary("sumo-gui" if gui else "sumo"), *sumo_args(seed, **kwargs)]
    if gui:
        cmd += ["--start", "true", "--quit-on-end", "true"]
    return cmd


class _Session:
    """This process's libsumo session (libsumo holds one simulation per process)."""

    key: tuple | None = None


def sumo_start(net_file: str | os.PathLike, seed: int, time_to_teleport_s: float = -1.0,
               state_file: str | os.PathLike | None = None):
    """This process's libsumo on ``net_file`` with ``--seed seed``; returns the ``libsumo`` module.

    Without ``state_file`` a running simulation with the same network, seed and teleport time is reused. With
    ``state_file`` the simulation is always (re)loaded from scratch with ``--load-state state_file`` (see the module
    docstring: ``simulation.loadState`` in a used simulation would make a rollout depend on what its process ran
    before, and sharding over workers would change results).

    :param time_to_teleport_s: SUMO ``--time-to-teleport`` [s] (-1: never).
    """
    ensure_sumo_home()
    import libsumo  # optional dependency (eclipse-sumo), imported only where SUMO runs

    key = (str(net_file), int(seed), float(time_to_teleport_s))
    if state_file is None and _Session.key == key:
        return libsumo
    args = sumo_args(seed, net_file=Path(net_file), time_to_teleport_s=time_to_teleport_s, load_state=state_file)
    if _Session.key is not None:
        settle_remote_control(libsumo)  # a reloaded state has the same vehicle IDs as the rollout before it
        libsumo.load(args)
    else:
        libsumo.start([sumo_binary("sumo"), *args])
    clear_static_cache(libsumo)
    _Session.key = key
    return libsumo


def settle_remote_control(conn) -> None:
    """Take one more SUMO step, with libsumo, so that libsumo forgets the vehicles ``moveToXY`` moved since its last
    step; call it right before closing or reloading a simulation in which ``moveToXY`` may have been sent.

    libsumo 1.28 keeps the vehicles of pending ``moveToXY`` calls (raw pointers in ``libsumo::Helper``'s
    remote-control list) until the next ``simulationStep``, and neither ``close`` nor ``load`` clears that list. The
    first step of the next simulation in the same process then works on the freed vehicles whenever it has vehicles
    of the same IDs already in it at that step (added through TraCI before the first step, a saved state loaded again,
    route-file vehicles SUMO has already built): a segmentation fault
    when the freed memory has been reused (valgrind: ``MSVehicle::getInfluencer`` in
    ``Helper::postProcessRemoteControl`` reading a vehicle freed by ``Simulation::close``; session 50, the CI
    failure of ``tests/test_sumo_controller.py``). A simulation about to end loses nothing by the extra step (SUMO
    steps past ``--end`` without complaint). A TraCI connection (one SUMO process per simulation) needs nothing: a
    no-op there, and for a simulation that is not running any more.

    :param conn: the ``libsumo`` module or a TraCI connection.
    """
    is_libsumo = getattr(conn, "isLibsumo", None)
    if is_libsumo is None or not is_libsumo():
        return
    try:
        conn.simulationStep()
    except Exception:  # noqa: BLE001 - nothing loaded (closed already, or SUMO stopped): nothing is pending either
        pass


def sumo_close() -> None:
    """Close this process's libsumo session started by :func:`sumo_start`, if any (after
    :func:`settle_remote_control`: in-loop rollouts move every agent with ``moveToXY``)."""
    if _Session.key is not None:
        import libsumo

        settle_remote_control(libsumo)
        libsumo.close()
        _Session.key = None
