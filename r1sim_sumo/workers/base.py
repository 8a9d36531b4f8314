"""The worker-pool contract shared by every backend: ordered ``map``, retries, statistics, errors.

A pool runs ``fn(task)`` (or ``fn(task, shared)``) for each task of a list on its workers, one task per
worker at a time, and returns the results **in task order**. Task ``i`` has the id ``i``; its result slot
is filled exactly once, so a retried task never produces a duplicate and a lost task is never silently
dropped (``map`` either returns every slot filled or raises).

Failures are of two kinds:

* **worker death** (the process segfaulted, was killed, called ``os._exit``; a Ray actor died): the worker
  is replaced by a fresh one and the task is retried, up to ``max_retries`` extra attempts;
* **a Python exception raised by the task**: by default not retried (Ray's convention: application errors
  are deterministic), ``retry_exceptions=True`` retries them like deaths (on a fresh worker).

When a task has used up its attempts :class:`TaskFailedError` names the task id, its description and the
last cause. Retries, restarts and failures are counted in :class:`PoolStats` (``pool.stats``).
"""

from __future__ import annotations

import time
import traceback
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

DEFAULT_MAX_RETRIES = 2


class TaskFailedError(RuntimeError):
    """A task failed on every attempt (or raised, when exceptions are not retried).

    :ivar task_id: index of the task in the list given to ``map``.
    :ivar cause: ``"died"`` (worker death) or ``"raised"`` (the task raised an exception).
    """

    def __init__(self, message: str, task_id: int, cause: str, attempts: int, remote_traceback: str = ""):
        super().__init__(message)
        self.task_id = task_id
        self.cause = cause
        self.attempts = attempts
        self.remote_traceback = remote_traceback


@dataclass
class TaskError:
    """An exception raised inside a worker, carried back as data (type name, message, formatted traceback)."""

    type_name: str
    message: str
    traceback: str


@dataclass
class PoolStats:
    """Counters of a pool over its lifetime (all ``map`` calls).

    :ivar retries: task attempts re-run after a failure (one per retry).
    :ivar worker_restarts: workers replaced after a death (or after a retried exception).
    :ivar failures: one ``{"task_id", "attempt", "cause", "detail"}`` per failed attempt.
    """

    backend: str
    workers: int
    tasks: int = 0
    completed: int = 0
    retries: int = 0
    worker_restarts: int = 0
    map_calls: int = 0
    wall_s: float = 0.0
    failures: list[dict] = field(default_factory=list)

    def summary(self) -> str:
        return (f"{self.backend} pool, {self.workers} worker(s): {self.completed}/{self.tasks} tasks done, "
                f"{self.retries} retried, {self.worker_restarts} worker restart(s), {self.wall_s:.1f} s in map")

    def to_dict(self) -> dict:
        return {"backend": self.backend, "workers": self.workers, "tasks": self.tasks, "completed": self.completed,
                "retries": self.retries, "worker_restarts": self.worker_restarts, "map_calls": self.map_calls,
                "wall_s": round(self.wall_s, 3), "failures": list(self.failures)}


def call_task(fn: Callable, task: Any, shared: Any, has_shared: bool) -> Any:
    """Run one task inside a worker; an exception comes back as a :class:`TaskError` value (not raised)."""
    try:
        return fn(task, shared) if has_shared else fn(task)
    except Exception as exc:  # noqa: BLE001 - every task error is reported to the parent, named
        return TaskError(type(exc).__name__, str(exc), traceback.format_exc())


def describe_task(task: Any, limit: int = 120) -> str:
    """A short description of a task for error messages: its ``label`` / ``describe()`` or its repr."""
    for attr in ("describe", "label"):
        v = getattr(task, attr, None)
        if v is not None:
            try:
                text = v() if callable(v) else v
            except Exception:  # noqa: BLE001 - a description must never hide the real error
                continue
            return str(text)[:limit]
    text = repr(task)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class WorkerPool(ABC):
    """``map(fn, tasks)`` over ``workers`` workers with per-task retries; a context manager (``close()`` on exit).

    Subclasses implement the slot primitives: ``_submit(slot, fn, task_id, task)`` starts one task on a
    worker slot and returns a handle, ``_wait(handles, timeout_s)`` returns the finished ones,
    ``_outcome(handle)`` gives ``("ok", value)`` or ``("died", detail)``, ``_restart(slot)`` replaces a
    dead worker, ``_poll_progress()`` forwards progress values reported by workers.
    """

    backend = "abstract"

    def __init__(self, workers: int, max_retries: int = DEFAULT_MAX_RETRIES, retry_exceptions: bool = False):
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        if max_retries < 0:
            raise ValueError(f"max_retries must be >= 0, got {max_retries}")
        self.workers = int(workers)
        self.max_retries = int(max_retries)
        self.retry_exceptions = bool(retry_exceptions)
        self.stats = PoolStats(self.backend, self.workers)
        self._closed = False
        self._on_progress: Callable[[Any], None] | None = None

    # ------------------------------------------------------------------ public API
    def map(self, fn: Callable, tasks: Sequence[Any], shared: Any = None,
            on_result: Callable[[int, Any], None] | None = None,
            on_progress: Callable[[Any], None] | None = None) -> list:
        """Run ``fn(task)`` (``fn(task, shared)`` when ``shared`` is given) for every task; results in task order.

        :param fn: a top-level (picklable) function.
        :param tasks: picklable task values; task ``i`` has id ``i``.
        :param shared: one object every task needs (e.g. a policy): sent to each worker once per ``map``
            call, not once per task.
        :param on_result: ``on_result(task_id, result)`` in the caller's process as each task finishes
            (completion order).
        :param on_progress: receives values workers send with :func:`r1sim_sumo.workers.report_progress`.
        :raises TaskFailedError: a task failed on every attempt (the message names it); the other
            workers are stopped and replaced, so the pool can still be used.
        """
        if self._closed:
            raise RuntimeError(f"{self.backend} pool is closed")
        tasks = list(tasks)
        n = len(tasks)
        self.stats.tasks += n
        self.stats.map_calls += 1
        t0 = time.perf_counter()
        results: list[Any] = [None] * n
        filled = [False] * n
        attempts = [0] * n
        pending: deque[int] = deque(range(n))
        free = deque(range(self.workers))
        inflight: dict[Any, tuple[int, int]] = {}  # handle -> (slot, task id)
        has_shared = shared is not None
        self._on_progress = on_progress
        self._begin_map(shared, has_shared)
        try:
            while pending or inflight:
                while pending and free:
                    slot, tid = free.popleft(), pending.popleft()
                    attempts[tid] += 1
                    inflight[self._submit(slot, fn, tid, tasks[tid])] = (slot, tid)
                done = self._wait(list(inflight), 0.2)
                self._poll_progress()
                for h in done:
                    slot, tid = inflight.pop(h)
                    kind, value = self._outcome(h)
                    if kind == "ok" and not isinstance(value, TaskError):
                        if filled[tid]:  # cannot happen with one handle per attempt; guard the invariant
                            raise RuntimeError(f"internal error: task {tid} produced two results")
                        results[tid], filled[tid] = value, True
                        self.stats.completed += 1
                        free.append(slot)
                        if on_result is not None:
                            on_result(tid, value)
                        continue
                    cause = "died" if kind == "died" else "raised"
                    detail = value if cause == "died" else f"{value.type_name}: {value.message}"
                    self.stats.failures.append({"task_id": tid, "attempt": attempts[tid], "cause": cause,
                                                "detail": str(detail)[:500]})
                    retryable = cause == "died" or self.retry_exceptions
                    if retryable:  # a fresh worker: a crashed simulator may have left state behind
                        self._restart(slot)
                        self.stats.worker_restarts += 1
                    free.append(slot)
                    if retryable and attempts[tid] <= self.max_retries:
                        self.stats.retries += 1
                        pending.appendleft(tid)
                        continue
                    raise self._failed(tid, tasks[tid], cause, attempts[tid], value)
            self._poll_progress(final=True)
        except BaseException:
            for h, (slot, _) in list(inflight.items()):  # stop the others: their results would be orphaned
                self._cancel(h, slot)
            raise
        finally:
            self._end_map()
            self._on_progress = None
            self.stats.wall_s += time.perf_counter() - t0
        missing = [i for i in range(n) if not filled[i]]
        if missing:  # the loop above cannot exit with holes; keep the invariant explicit
            raise RuntimeError(f"internal error: tasks {missing[:10]} finished without a result")
        return results

    def close(self) -> None:
        """Stop the workers (idempotent)."""
        if not self._closed:
            self._closed = True
            self._shutdown()

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # best effort: never leave worker processes behind
        try:
            self.close()
        except Exception:  # noqa: BLE001
            pass

    # ------------------------------------------------------------------ helpers
    def _failed(self, tid: int, task: Any, cause: str, attempts: int, value: Any) -> TaskFailedError:
        what = f"task {tid} ({describe_task(task)})"
        if cause == "died":
            msg = (f"{what}: its worker died on each of {attempts} attempt(s) (last: {value}); "
                   f"raise max_retries (now {self.max_retries}) if the failures are transient")
            return TaskFailedError(msg, tid, cause, attempts)
        msg = f"{what} raised {value.type_name}: {value.message}\n--- worker traceback ---\n{value.traceback}"
        return TaskFailedError(msg, tid, cause, attempts, value.traceback)

    def _emit_progress(self, value: Any) -> None:
        if self._on_progress is not None:
            self._on_progress(value)

    def _begin_map(self, shared: Any, has_shared: bool) -> None:
        self._shared, self._has_shared = shared, has_shared

    def _end_map(self) -> None:
        self._shared, self._has_shared = None, False

    def _poll_progress(self, final: bool = False) -> None:
        return None

    # ------------------------------------------------------------------ backend primitives
    @abstractmethod
    def _submit(self, slot: int, fn: Callable, task_id: int, task: Any) -> Any: ...

    @abstractmethod
    def _wait(self, handles: list, timeout_s: float) -> list: ...

    @abstractmethod
    def _outcome(self, handle: Any) -> tuple[str, Any]: ...

    @abstractmethod
    def _restart(self, slot: int) -> None: ...

    @abstractmethod
    def _cancel(self, handle: Any, slot: int) -> None: ...

    @abstractmethod
    def _shutdown(self) -> None: ...
