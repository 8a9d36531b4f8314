"""Shared start of the session-61 roundabout diagnostics: the bundled roundabout at full demand in libsumo,
native SUMO or the position drive of the shipped policy with every default."""
import libsumo as conn
import torch

from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command


def start_roundabout(end_s: float, native: bool, seed: int = 0):
    """(libsumo, the controller or None for native SUMO), the simulation started and running to ``end_s`` [s]."""
    torch.set_num_threads(1)
    ensure_sumo_home()
    conn.start(sumo_command(seed, sumocfg=network_files("roundabout")["sumocfg"], end_s=end_s + 1))
    ctrl = None if native else SumoController(conn, load_policy(None), control="all", seed=seed, safety="krauss",
                                              drive="position")
    return conn, ctrl


def close(conn) -> None:
    settle_remote_control(conn)
    conn.close()
