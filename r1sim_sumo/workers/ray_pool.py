"""``ray`` backend: one Ray actor per worker, on this machine or on a Ray cluster.

``ray.init()`` starts a local Ray instance (or joins the cluster named by the ``RAY_ADDRESS`` environment
variable); ``ray_address="auto"`` / ``"ray://head:10001"`` joins an existing cluster (see
``docs/running_on_a_cluster.md``). If Ray is already initialised in this process it is reused.

Each actor (``num_cpus=cpus_per_worker``, so Ray sets its ``OMP_NUM_THREADS``) holds at most one simulator,
because an actor is its own process. The scheduler is the shared one of :class:`WorkerPool` (one task per
actor at a time, ``ray.wait`` on the running tasks); an actor that dies (``RayActorError``: the process
crashed or was killed, the node was lost) is killed for good and replaced by a new actor, and its task is
retried. The ``shared`` object of a ``map`` call is put in the object store once and fetched once per actor.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable
from typing import Any

from r1sim_sumo.workers.base import DEFAULT_MAX_RETRIES, TaskError, WorkerPool, call_task


def import_ray():
    """``import ray`` with an installation hint when it is missing."""
    try:
        import ray
    except ImportError as exc:
        raise ImportError("the 'ray' backend needs Ray: pip install 'ray>=2.9' (or use --backend process)") from exc
    return ray


class _Worker:
    """The actor class (wrapped by ``ray.remote`` when the pool starts): runs tasks, caches the shared object."""

    def __init__(self) -> None:
        self._shared: dict[str, Any] = {}

    def ping(self) -> int:
        return os.getpid()

    def run(self, fn: Callable, task: Any, key: str | None, boxed_ref: list | None) -> Any:
        if key is None:
            return call_task(fn, task, None, False)
        if key not in self._shared:
            import ray

            self._shared.clear()
            self._shared[key] = ray.get(boxed_ref[0])  # boxed: Ray would otherwise resolve it on every call
        return call_task(fn, task, self._shared[key], True)


def _init_ray(ray, address: str | None, kw: dict, cpus_needed: int) -> None:
    """Join ``address`` / ``RAY_ADDRESS`` / a cluster already running on this node, else start a local instance
    with at least ``cpus_needed`` logical CPUs (so ``--workers`` above the core count still starts)."""
    if address is not None or os.environ.get("RAY_ADDRESS"):
        ray.init(address=address, **kw)
        return
    try:
        ray.init(address="auto", **kw)  # a cluster started with `ray start` on this node
        return
    except ConnectionError:
        pass
    kw.setdefault("include_dashboard", False)
    kw.setdefault("num_cpus", max(os.cpu_count() or 1, cpus_needed))
    ray.init(**kw)


class RayPool(WorkerPool):
    """``workers`` Ray actors.

    :param ray_address: ``None`` = ``ray.init()`` (local instance, or ``RAY_ADDRESS``); else the address
        passed to ``ray.init(address=...)``, e.g. ``"auto"`` on a cluster node or ``"ray://head:10001"``.
    :param cpus_per_worker: CPUs Ray reserves per actor.
    :param init_kwargs: extra ``ray.init`` arguments (e.g. ``runtime_env``) when this pool starts Ray.
    :param startup_timeout_s: how long to wait for the actors to start before naming the missing resources.
    """

    backend = "ray"

    def __init__(self, workers: int = 2, max_retries: int = DEFAULT_MAX_RETRIES, retry_exceptions: bool = False,
                 ray_address: str | None = None, cpus_per_worker: float = 1.0, init_kwargs: dict | None = None,
                 startup_timeout_s: float = 300.0):
        super().__init__(workers, max_retries, retry_exceptions)
        ray = import_ray()
        self._ray = ray
        self._owns_ray = False
        if not ray.is_initialized():
            _init_ray(ray, ray_address, dict(init_kwargs or {}), int(workers * cpus_per_worker + 0.999))
            self._owns_ray = True
        self._actor_cls = ray.remote(num_cpus=cpus_per_worker, max_restarts=0)(_Worker)
        self._actors = [self._actor_cls.remote() for _ in range(self.workers)]
        self._ref: Any = None
        self._key: str | None = None
        try:
            ray.get([a.ping.remote() for a in self._actors], timeout=startup_timeout_s)
        except ray.exceptions.GetTimeoutError:
            self._shutdown()
            raise RuntimeError(f"ray backend: {self.workers} actor(s) of {cpus_per_worker} CPU did not start within "
                               f"{startup_timeout_s:.0f} s; the cluster offers {ray.cluster_resources()}. Use fewer "
                               "--workers or add nodes (ray start --address=HEAD:6379).") from None

    def _begin_map(self, shared: Any, has_shared: bool) -> None:
        super()._begin_map(shared, has_shared)
        self._key = uuid.uuid4().hex if has_shared else None
        self._ref = self._ray.put(shared) if has_shared else None

    def _end_map(self) -> None:
        super()._end_map()
        self._key, self._ref = None, None

    def _submit(self, slot: int, fn: Callable, task_id: int, task: Any):
        box = [self._ref] if self._key is not None else None
        return self._actors[slot].run.remote(fn, task, self._key, box)

    def _wait(self, handles: list, timeout_s: float) -> list:
        ready, _ = self._ray.wait(handles, num_returns=1, timeout=timeout_s)
        return ready

    def _outcome(self, handle) -> tuple[str, Any]:
        ray = self._ray
        try:
            return "ok", ray.get(handle)
        except ray.exceptions.RayActorError as exc:
            return "died", f"Ray actor died ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        except ray.exceptions.RayError as exc:  # e.g. the task or its result could not be (de)serialised
            return "ok", TaskError(type(exc).__name__, str(exc), "")

    def _restart(self, slot: int) -> None:
        try:
            self._ray.kill(self._actors[slot], no_restart=True)
        except Exception:  # noqa: BLE001 - already gone
            pass
        self._actors[slot] = self._actor_cls.remote()

    def _cancel(self, handle, slot: int) -> None:
        self._restart(slot)

    def _shutdown(self) -> None:
        for a in getattr(self, "_actors", []):
            try:
                self._ray.kill(a, no_restart=True)
            except Exception:  # noqa: BLE001
                pass
        self._actors = []
        if self._owns_ray and self._ray.is_initialized():
            self._ray.shutdown()
