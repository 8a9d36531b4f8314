"""``process`` backend: one spawned process per worker (the default on one machine).

libsumo holds one simulation per process, so each worker is its own process started with the ``spawn``
method (a fresh interpreter: no simulator state, torch thread pool or open file is inherited from the
parent). Each worker slot is a ``concurrent.futures.ProcessPoolExecutor(max_workers=1)``: when a worker
dies its executor breaks with ``BrokenProcessPool``, which tells exactly which task was running on it; the
slot gets a new executor (a new process) and the task is retried.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue as queue_mod
import uuid
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from r1sim_sumo.workers.base import DEFAULT_MAX_RETRIES, TaskError, WorkerPool, call_task
from r1sim_sumo.workers.progress import set_progress_sink

# ---------------------------------------------------------------------------- worker side

_SHARED: dict[str, Any] = {}  # key of the current map call -> its shared object (one entry kept)


def _init_worker(progress_queue, threads: int | None) -> None:
    """Runs once in each new worker process: progress channel and thread limits (before torch is imported)."""
    if threads is not None:
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            os.environ[var] = str(threads)
        import sys

        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(threads)
    set_progress_sink(progress_queue.put if progress_queue is not None else None)


def _run_in_worker(fn: Callable, task: Any, key: str | None, payload: tuple | None) -> Any:
    """Worker entry: cache the shared object of this map call (sent once per worker), run the task."""
    if payload is not None:
        _SHARED.clear()
        _SHARED[key] = payload[0]
    if key is None:
        return call_task(fn, task, None, False)
    if key not in _SHARED:
        raise RuntimeError(f"internal error: shared object {key} was never sent to this worker")
    return call_task(fn, task, _SHARED[key], True)


# ---------------------------------------------------------------------------- parent side


class ProcessPool(WorkerPool):
    """``workers`` spawned processes on this machine.

    :param threads_per_worker: sets ``OMP_NUM_THREADS`` (and torch's thread count) in each worker; ``None``
        leaves the defaults (then give tasks their own ``torch.set_num_threads``).
    :param start_method: ``"spawn"`` (default) or ``"forkserver"``; never ``"fork"`` (libsumo/torch state).
    """

    backend = "process"

    def __init__(self, workers: int = 2, max_retries: int = DEFAULT_MAX_RETRIES, retry_exceptions: bool = False,
                 threads_per_worker: int | None = 1, start_method: str = "spawn"):
        if start_method not in ("spawn", "forkserver"):
            raise ValueError(f"start_method must be 'spawn' or 'forkserver' (fork would copy simulator state), "
                             f"got {start_method!r}")
        super().__init__(workers, max_retries, retry_exceptions)
        self._ctx = mp.get_context(start_method)
        self._queue = self._ctx.Queue()
        self._threads = threads_per_worker
        self._slots: list[ProcessPoolExecutor] = [self._new_executor() for _ in range(self.workers)]
        self._slot_key: list[str | None] = [None] * self.workers  # shared object each worker holds
        self._key: str | None = None

    def _new_executor(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(max_workers=1, mp_context=self._ctx, initializer=_init_worker,
                                   initargs=(self._queue, self._threads))

    def _begin_map(self, shared: Any, has_shared: bool) -> None:
        super()._begin_map(shared, has_shared)
        self._key = uuid.uuid4().hex if has_shared else None

    def _submit(self, slot: int, fn: Callable, task_id: int, task: Any) -> Future:
        payload = None
        if self._key is not None and self._slot_key[slot] != self._key:
            payload = (self._shared,)
            self._slot_key[slot] = self._key
        try:
            return self._slots[slot].submit(_run_in_worker, fn, task, self._key, payload)
        except BrokenProcessPool:  # the worker died between two tasks: replace it and submit again
            self._restart(slot)
            return self._submit(slot, fn, task_id, task)

    def _wait(self, handles: list, timeout_s: float) -> list:
        done, _ = wait(handles, timeout=timeout_s, return_when=FIRST_COMPLETED)
        return list(done)

    def _outcome(self, handle: Future) -> tuple[str, Any]:
        exc = handle.exception()
        if exc is None:
            return "ok", handle.result()
        if isinstance(exc, BrokenProcessPool):
            return "died", f"worker process died ({exc})"
        # the task or its result could not be pickled, or fn could not be imported in the worker
        return "ok", TaskError(type(exc).__name__, f"{exc} (sending the task or its result failed)", "")

    def _restart(self, slot: int) -> None:
        _terminate(self._slots[slot])
        self._slots[slot] = self._new_executor()
        self._slot_key[slot] = None

    def _cancel(self, handle: Future, slot: int) -> None:
        if not handle.done():
            self._restart(slot)

    def _poll_progress(self, final: bool = False) -> None:
        """Forward queued progress values; ``final`` (end of a map) waits briefly for values still in flight: a
        worker's queue feeder thread may deliver them after the task's result, which travels on another pipe."""
        while True:
            try:
                value = self._queue.get(timeout=0.1) if final else self._queue.get_nowait()
            except queue_mod.Empty:
                return
            except (OSError, ValueError, EOFError):  # queue closed
                return
            self._emit_progress(value)

    def _shutdown(self) -> None:
        for ex in self._slots:
            _terminate(ex, graceful=True)
        self._slots = []
        try:
            self._queue.close()
            self._queue.join_thread()
        except (OSError, ValueError, AssertionError):
            pass


def _terminate(ex: ProcessPoolExecutor, graceful: bool = False) -> None:
    """Stop an executor and its process (``graceful``: let an idle worker exit by itself first; a running
    task is abandoned either way)."""
    procs = list((getattr(ex, "_processes", None) or {}).values())
    if graceful and _idle(ex):
        ex.shutdown(wait=True)
    else:
        ex.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(timeout=10)
        if p.is_alive():
            p.kill()
            p.join(timeout=5)


def _idle(ex: ProcessPoolExecutor) -> bool:
    """No work item is pending or running in this executor (its worker will exit on the shutdown sentinel)."""
    return not getattr(ex, "_pending_work_items", {})
