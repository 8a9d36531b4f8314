"""``make_pool(backend, workers)`` and the ``--backend / --workers / --ray-address`` command-line options."""

from __future__ import annotations

import argparse
import os

from r1sim_sumo.workers.base import DEFAULT_MAX_RETRIES, WorkerPool

BACKENDS = ("local", "process", "ray")


def default_backend(workers: int) -> str:
    """``local`` for one worker (no process start-up cost), ``process`` for more."""
    return "local" if workers <= 1 else "process"


def make_pool(backend: str | None = None, workers: int = 1, ray_address: str | None = None,
              max_retries: int = DEFAULT_MAX_RETRIES, retry_exceptions: bool = False,
              threads_per_worker: int | None = 1, **backend_kwargs) -> WorkerPool:
    """A worker pool: ``local`` (in this process), ``process`` (spawned processes) or ``ray`` (Ray actors).

    :param backend: one of :data:`BACKENDS`; ``None`` = :func:`default_backend` of ``workers``.
    :param workers: number of workers (simulators running at once).
    :param ray_address: ``ray`` only: cluster address for ``ray.init(address=...)`` (``"auto"``,
        ``"ray://head:10001"``); ``None`` starts a local Ray instance unless ``RAY_ADDRESS`` is set.
    :param max_retries: extra attempts of a task whose worker died (default 2).
    :param retry_exceptions: also retry tasks that raised (on a fresh worker).
    :param threads_per_worker: ``process`` only: ``OMP_NUM_THREADS`` of each worker (Ray sets it from the
        actor's CPUs).
    """
    backend = backend or default_backend(workers)
    if backend == "local":
        from r1sim_sumo.workers.local import LocalPool

        return LocalPool(workers, max_retries, retry_exceptions)
    if backend == "process":
        from r1sim_sumo.workers.process import ProcessPool

        return ProcessPool(workers, max_retries, retry_exceptions, threads_per_worker=threads_per_worker,
                           **backend_kwargs)
    if backend == "ray":
        from r1sim_sumo.workers.ray_pool import RayPool

        return RayPool(workers, max_retries, retry_exceptions, ray_address=ray_address, **backend_kwargs)
    raise ValueError(f"backend {backend!r} unknown; choose one of {', '.join(BACKENDS)}")


def add_pool_arguments(p: argparse.ArgumentParser, default_workers: int = 1, what: str = "tasks") -> None:
    """Add ``--backend``, ``--workers``, ``--ray-address`` and ``--max-retries`` to a sub-command."""
    p.add_argument("--workers", type=int, default=default_workers,
                   help=f"workers running {what} in parallel (default {default_workers})")
    p.add_argument("--backend", choices=BACKENDS, default=None,
                   help="local (in this process) | process (spawned processes, default for --workers > 1) | "
                        "ray (Ray actors; local instance or a cluster, see --ray-address)")
    p.add_argument("--ray-address", default=os.environ.get("R1SIM_RAY_ADDRESS"),
                   help="ray backend: cluster address, e.g. 'auto' on a cluster node or ray://HEAD:10001 "
                        "(default: $R1SIM_RAY_ADDRESS, else $RAY_ADDRESS, else a local Ray instance)")
    p.add_argument("--max-retries", type=int, default=DEFAULT_MAX_RETRIES,
                   help=f"retries of a task whose worker died (default {DEFAULT_MAX_RETRIES})")


def pool_from_args(args: argparse.Namespace, **kwargs) -> WorkerPool:
    """The pool named by the options of :func:`add_pool_arguments`."""
    if args.workers < 1:
        raise ValueError(f"--workers {args.workers}: must be >= 1")
    return make_pool(args.backend, args.workers, ray_address=args.ray_address, max_retries=args.max_retries, **kwargs)
