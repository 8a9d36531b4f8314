"""Data-parallel training helpers (``torch.distributed`` + ``DistributedDataParallel``), launched by ``torchrun``.

::

    torchrun --nproc_per_node 2 -m r1sim_sumo.cli pretrain --config configs/pretrain.yaml        # one machine
    torchrun --nnodes 4 --nproc_per_node 8 --rdzv_backend c10d --rdzv_endpoint HEAD:29500 \\
             -m r1sim_sumo.cli pretrain --config configs/pretrain.yaml                          # a cluster

``torchrun`` sets ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT``;
:func:`init_from_env` reads them (no variable = one process, nothing initialised). The process group uses
``gloo`` on CPU and ``nccl`` when the model runs on a CUDA device.

**Same global batch as one process.** Every rank builds the *same* global batch (same scene indices, same
history-drop draw), keeps its contiguous slice of the scenes (:func:`shard_batch`, padding trimmed so the
slice equals collating those scenes alone) and computes the mean loss over its valid tokens. The loss each
rank back-propagates is scaled by ``n_rank * world_size / n_global`` (token counts all-reduced), so the
gradient DDP averages is the gradient of the mean over *all* valid tokens of the global batch, as in one
process (:func:`global_token_mean`). Dropout masks are drawn per rank, so with ``dropout > 0`` the runs are
statistically, not bitwise, equivalent; with ``dropout = 0`` they agree to float rounding.

Only rank 0 (:attr:`DistInfo.is_main`) writes logs, checkpoints and the vocabulary.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

ENV_VARS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


@dataclass(frozen=True)
class DistInfo:
    """This process's place in the job: ``rank`` of ``world_size`` (``local_rank`` on its node)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    backend: str | None = None  # "gloo" / "nccl"; None when not distributed

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def _env_int(name: str) -> int:
    value = os.environ.get(name)
    if value is None:
        raise RuntimeError(f"distributed training: WORLD_SIZE is set but {name} is not; launch with torchrun "
                           f"(which sets {', '.join(ENV_VARS)}) or set them all")
    try:
        return int(value)
    except ValueError:
        raise RuntimeError(f"distributed training: environment variable {name}={value!r} is not an integer") from None


def init_from_env(device: str = "cpu") -> DistInfo:
    """Join the process group described by torchrun's environment variables; one process when absent.

    :param device: where the model runs; ``"cuda..."`` selects ``nccl`` and ``cuda:LOCAL_RANK``.
    """
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if world <= 1:
        return DistInfo()
    rank, local_rank = _env_int("RANK"), _env_int("LOCAL_RANK")
    use_cuda = str(device).startswith("cuda") and torch.cuda.is_available()
    backend = "nccl" if use_cuda else "gloo"
    if not dist.is_initialized():
        for var in ("MASTER_ADDR", "MASTER_PORT"):
            if not os.environ.get(var):
                raise RuntimeError(f"distributed training: {var} is not set; launch with torchrun or export it")
        dist.init_process_group(backend, rank=rank, world_size=world)
    if use_cuda:
        torch.cuda.set_device(local_rank)
    return DistInfo(rank=rank, world_size=world, local_rank=local_rank, backend=backend)


def wrap_model(model: torch.nn.Module, info: DistInfo) -> torch.nn.Module:
    """``DistributedDataParallel(model)`` when distributed (else ``model`` itself); keep the bare model for
    saving and evaluation."""
    if not info.enabled:
        return model
    from torch.nn.parallel import DistributedDataParallel

    dev = next(model.parameters()).device
    if dev.type == "cuda":
        return DistributedDataParallel(model, device_ids=[dev.index], output_device=dev.index)
    return DistributedDataParallel(model)


def shard_rows(batch_size: int, info: DistInfo) -> range:
    """The contiguous scene rows ``[lo, hi)`` of the global batch that this rank trains on."""
    if batch_size < info.world_size:
        raise ValueError(f"batch_size {batch_size} is smaller than the number of processes {info.world_size}: "
                         "every rank needs at least one scene; raise batch_size or use fewer processes")
    base, extra = divmod(batch_size, info.world_size)
    lo = info.rank * base + min(info.rank, extra)
    return range(lo, lo + base + (1 if info.rank < extra else 0))


def shard_batch(batch, info: DistInfo):
    """This rank's rows of a collated :class:`~r1sim_sumo.tokens.batch.SceneBatch`, padding trimmed to the
    largest agent / map-token count among them (equal to collating those scenes alone)."""
    if not info.enabled:
        return batch
    rows = shard_rows(int(batch.agent_mask.shape[0]), info)
    sl = slice(rows.start, rows.stop)
    a = max(int(batch.agent_mask[sl].sum(1).max()), 1)  # agents are packed at the front of each row
    m = max(int(batch.map_mask[sl].sum(1).max()), 1)
    fields = {}
    for name, t in batch._asdict().items():
        t = t[sl]
        if name.startswith("map_"):
            t = t[:, :m]
        else:
            t = t[:, :a]
        fields[name] = t
    return type(batch)(**fields)


def shard_like(t: torch.Tensor, batch, info: DistInfo) -> torch.Tensor:
    """This rank's rows of a per-agent tensor ``[B, A, ...]`` aligned with the *unsharded* ``batch``, trimmed as
    :func:`shard_batch` trims that batch."""
    if not info.enabled:
        return t
    rows = shard_rows(int(batch.agent_mask.shape[0]), info)
    sl = slice(rows.start, rows.stop)
    a = max(int(batch.agent_mask[sl].sum(1).max()), 1)
    return t[sl, :a]


def count_loss_tokens(batch, n_steps: int) -> int:
    """Tokens :meth:`TrafficPolicy.loss` averages over (valid token, real agent, valid start pose)."""
    valid = batch.agent_token_valid.bool() & batch.agent_mask.bool().unsqueeze(-1) & batch.pose_valid[:, :, :n_steps].bool()
    return int(valid.sum())


def global_token_mean(loss: torch.Tensor, acc: torch.Tensor, n_local: int,
                      info: DistInfo) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Turn a rank's mean loss / accuracy over its ``n_local`` tokens into global-batch quantities.

    :return: ``(loss_to_backward, global_mean_loss, global_accuracy)``: back-propagating the first on every
        rank (DDP averages gradients over ranks) gives the gradient of the mean loss over all tokens of the
        global batch; the other two (detached) are what one process would log.
    """
    if not info.enabled:
        return loss, loss.detach(), acc
    sums = torch.tensor([float(n_local), float(loss.detach()) * n_local, float(acc) * n_local], dtype=torch.float64)
    dist.all_reduce(sums)
    n_global = max(float(sums[0]), 1.0)
    scale = n_local * info.world_size / n_global
    return loss * scale, torch.tensor(sums[1].item() / n_global), torch.tensor(sums[2].item() / n_global)


def barrier(info: DistInfo) -> None:
    """Wait for every rank (no-op in one process)."""
    if info.enabled:
        dist.barrier()


def shutdown(info: DistInfo) -> None:
    """Leave the process group (call once at the end of training)."""
    if info.enabled and dist.is_initialized():
        dist.destroy_process_group()
