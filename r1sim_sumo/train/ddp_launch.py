"""Local launcher of distributed pretraining (tests, single-machine checks; no torchrun).

:func:`spawn_pretrain` runs ``pretrain(cfg)`` on ``world_size`` CPU processes (gloo) with the environment variables
torchrun would set, so the code path is torchrun's (:mod:`r1sim_sumo.train.ddp`). On a cluster use ``torchrun``
(see :mod:`r1sim_sumo.train.ddp` and ``docs/running_on_a_cluster.md``). Kept apart from :mod:`~r1sim_sumo.train.ddp`
because it imports the pretraining loop, which imports ``ddp``.
"""

from __future__ import annotations

import os
import socket
from dataclasses import asdict

import torch.multiprocessing as tmp

from r1sim_sumo.train.pretrain import PretrainConfig, pretrain


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _pretrain_rank(rank: int, world_size: int, port: int, cfg_dict: dict) -> None:
    """One rank of :func:`spawn_pretrain`: torchrun's environment variables, then ``pretrain``."""
    os.environ.update({"RANK": str(rank), "LOCAL_RANK": str(rank), "WORLD_SIZE": str(world_size),
                       "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)})
    pretrain(PretrainConfig(**cfg_dict), progress=False)


def spawn_pretrain(cfg: PretrainConfig, world_size: int = 2) -> None:
    """Run ``pretrain(cfg)`` on ``world_size`` local CPU processes (gloo), the code path torchrun takes."""
    tmp.spawn(_pretrain_rank, args=(world_size, _free_port(), asdict(cfg)), nprocs=world_size, join=True)
