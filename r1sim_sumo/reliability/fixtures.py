"""Small, fast inputs for reliability checks: toy scenarios, hand-written SUMO networks, a toy vocabulary,
an untrained checkpoint, a tiny dataset. Everything is built in a caller-given folder; nothing is downloaded.

Frames as everywhere: metres, x east, y north, yaw radians CCW from +x, box centres, 10 Hz.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from r1sim_sumo.model.checkpoint import save_checkpoint
from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.policy import TrafficPolicy
from r1sim_sumo.model.synthetic import synthetic_vocab
from r1sim_sumo.scenario import N_WINDOW_10HZ, AgentTracks, MapPolylines, Scenario, write_dataset
from r1sim_sumo.tokens.motion_vocab import MotionVocab


def straight_map(length_m: float = 200.0) -> MapPolylines:
    """Two eastbound lanes (centres at y = -1.75 and 1.75 m) and their road edges (y = -3.5, 3.5 m)."""
    xs = np.linspace(0.0, length_m, 21)
    lanes = [np.stack([xs, np.full_like(xs, y)], 1) for y in (-1.75, 1.75)]
    edges = [np.stack([xs, np.full_like(xs, y)], 1) for y in (-3.5, 3.5)]
    return MapPolylines.from_lists(lanes + edges, [0, 0, 1, 1], ["l_0", "l_1", "e#right", "e#left"],
                                   [13.9, 13.9, 0.0, 0.0], [3.5, 3.5, 0.0, 0.0], successors=[(0, 1)])


def toy_scenario(num_agents: int = 4, seed: int = 0, num_steps: int = N_WINDOW_10HZ) -> Scenario:
    """Constant-velocity vehicles on :func:`straight_map` (8-14 m/s, 8 m apart per lane), all valid."""
    rng = np.random.default_rng(seed)
    a = AgentTracks.empty(num_agents, num_steps)
    a.ids = np.array([f"veh_{i}" for i in range(num_agents)])
    t = np.arange(num_steps) * 0.1  # [T] s
    v = rng.uniform(8.0, 14.0, num_agents)  # [A] m/s
    x0 = 10.0 + 8.0 * (np.arange(num_agents) // 2)
    a.x_m[:] = x0[:, None] + v[:, None] * t
    a.y_m[:] = np.where(np.arange(num_agents) % 2 == 0, -1.75, 1.75)[:, None]
    a.speed_mps[:] = v[:, None]
    a.vx_mps[:] = v[:, None]
    a.valid[:] = True
    return Scenario(agents=a, map=straight_map(max(200.0, float(a.x_m.max()) + 20.0)),
                    metadata={"source": "test", "network": "straight", "seed": seed})


def toy_vocab():
    """A small synthetic motion vocabulary (128/32/32 tokens), the one the tests' untrained policy uses."""
    tr = synthetic_vocab((128, 32, 32))
    return MotionVocab.from_traj({i: t.numpy() for i, t in enumerate(tr)})


def toy_checkpoint(folder: Path, seed: int = 0, **overrides) -> Path:
    """An untrained nano-sized policy (``overrides`` e.g. ``agent_layers=1``) saved as a checkpoint folder."""
    vocab = toy_vocab()
    torch.manual_seed(seed)
    cfg = PolicyConfig.preset("nano", vocab_sizes=vocab.sizes, **overrides)
    model = TrafficPolicy(cfg, [torch.as_tensor(vocab.traj[i]) for i in range(3)])
    return save_checkpoint(folder, model, vocab, extra={"note": "untrained reliability fixture"})


def toy_dataset(folder: Path, n: int = 8, num_agents: int = 4, seed: int = 0) -> Path:
    """A dataset folder of ``n`` toy scenarios (written with :func:`~r1sim_sumo.scenario.write_dataset`)."""
    return write_dataset(folder, [toy_scenario(num_agents, seed + i) for i in range(n)], shard_size=4)


# ---------------------------------------------------------------------------- hand-written SUMO networks

_NET_HEAD = ('<?xml version="1.0" encoding="UTF-8"?>\n<net version="1.20" junctionCornerDetail="5" limitTurnSpeed="5.50">\n'
             '    <location netOffset="0.00,0.00" convBoundary="0.00,-50.00,100.00,50.00" origBoundary="0,0,100,0" projParameter="!"/>\n')


def _edge(eid: str, frm: str, to: str, shape: str, length: float, allow: str = "") -> str:
    al = f' allow="{allow}"' if allow else ""
    return (f'    <edge id="{eid}" from="{frm}" to="{to}" priority="1">\n'
            f'        <lane id="{eid}_0" index="0"{al} speed="13.89" length="{length:.2f}" shape="{shape}"/>\n    </edge>\n')


def _junction(jid: str, x: float, y: float, inc: str = "") -> str:
    return (f'    <junction id="{jid}" type="dead_end" x="{x:.2f}" y="{y:.2f}" incLanes="{inc}" intLanes="" '
            f'shape="{x:.2f},{y - 3.2:.2f} {x:.2f},{y:.2f}"/>\n')


def write_net(path: Path, kind: str) -> Path:
    """Write a small hand-written ``.net.xml`` of ``kind``: ``ok`` (one 100 m eastbound lane),
    ``pedestrian_only`` (sidewalks only), ``zero_length`` (``ok`` + a lane of zero length),
    ``overlapping`` (two junctions at the same point, and a northbound lane crossing the eastbound one
    without a junction)."""
    body = _edge("a", "n0", "n1", "0.00,-1.60 100.00,-1.60", 100.0)
    juncs = _junction("n0", 0, 0) + _junction("n1", 100, 0, "a_0")
    if kind == "pedestrian_only":
        body = _edge("a", "n0", "n1", "0.00,-1.60 100.00,-1.60", 100.0, allow="pedestrian")
    elif kind == "zero_length":
        body += _edge("z", "n1", "m0", "100.00,-1.60 100.00,-1.60", 0.0)
        juncs += _junction("m0", 100, 0)
    elif kind == "overlapping":
        body += _edge("b", "m0", "m1", "50.00,-50.00 50.00,50.00", 100.0)
        juncs += _junction("m0", 100, 0) + _junction("m1", 50, 50, "b_0")  # m0 sits on n1
    elif kind != "ok":
        raise ValueError(f"unknown net kind {kind!r}")
    path.write_text(_NET_HEAD + body + juncs + "</net>\n")
    return path
