"""Worker pools: run many simulations / evaluations at once, on one machine or a Ray cluster.

One simulator per worker (libsumo holds one simulation per process). Backends:

* ``local``: in the calling process, sequential (tests, ``--workers 1``);
* ``process``: spawned processes on this machine (the default for ``--workers > 1``);
* ``ray``: Ray actors on a local Ray instance or a cluster (``ray_address``).

::

    from r1sim_sumo.workers import make_pool

    with make_pool("process", workers=4) as pool:
        results = pool.map(run_one, tasks)          # results[i] belongs to tasks[i]
        print(pool.stats.summary())                 # tasks done, retries, worker restarts

A worker that dies is replaced and its task retried (``max_retries``, default 2); a task that keeps failing
raises :class:`TaskFailedError` naming it. ``fn`` must be a top-level (importable) function.
"""

from r1sim_sumo.workers.base import DEFAULT_MAX_RETRIES, PoolStats, TaskError, TaskFailedError, WorkerPool
from r1sim_sumo.workers.factory import (
           BACKENDS,
           add_pool_arguments,
           default_backend,
           make_pool,
           pool_from_args,
)
from r1sim_sumo.workers.progress import report_progress

__all__ = ["BACKENDS", "DEFAULT_MAX_RETRIES", "PoolStats", "TaskError", "TaskFailedError", "WorkerPool",
           "add_pool_arguments", "default_backend", "make_pool", "pool_from_args", "report_progress"]
