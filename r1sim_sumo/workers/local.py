"""``local`` backend: tasks run one after another in the calling process (tests, debugging, ``--workers 1``).

Results, ordering and error messages are those of the other backends, so a sharded run can be compared
with it. A worker death cannot be survived here (it is the caller's process); a task that raises is
retried only with ``retry_exceptions=True``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from r1sim_sumo.workers.base import DEFAULT_MAX_RETRIES, WorkerPool, call_task
from r1sim_sumo.workers.progress import set_progress_sink


class _Done:
    """Handle of a task that already ran: its result (or TaskError)."""

    __slots__ = ("value",)

    def __init__(self, value: Any):
        self.value = value


class LocalPool(WorkerPool):
    """In-process pool; ``workers`` is recorded for reports but tasks run sequentially."""

    backend = "local"

    def __init__(self, workers: int = 1, max_retries: int = DEFAULT_MAX_RETRIES, retry_exceptions: bool = False):
        super().__init__(workers, max_retries, retry_exceptions)

    def _submit(self, slot: int, fn: Callable, task_id: int, task: Any) -> _Done:
        prev = set_progress_sink(self._emit_progress)
        try:
            return _Done(call_task(fn, task, self._shared, self._has_shared))
        finally:
            set_progress_sink(prev)

    def _wait(self, handles: list, timeout_s: float) -> list:
        return handles

    def _outcome(self, handle: _Done) -> tuple[str, Any]:
        return "ok", handle.value

    def _restart(self, slot: int) -> None:
        return None

    def _cancel(self, handle: Any, slot: int) -> None:
        return None

    def _shutdown(self) -> None:
        return None
