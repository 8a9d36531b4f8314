"""Progress values sent from inside a task to the caller of ``pool.map(..., on_progress=...)``.

A task calls :func:`report_progress` (e.g. simulated seconds done); the value reaches ``on_progress`` in the
caller's process: directly (``local``), through a queue (``process``). Ray workers have no channel: there
the call is a no-op and progress is seen per finished task (``on_result``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

_SINK: Callable[[Any], None] | None = None


def report_progress(value: Any) -> None:
    """Send ``value`` (small and picklable) to the pool's caller; a no-op when nobody listens."""
    if _SINK is not None:
        _SINK(value)


def set_progress_sink(sink: Callable[[Any], None] | None) -> Callable[[Any], None] | None:
    """Install the function that receives progress values in this process; returns the previous one."""
    global _SINK
    prev, _SINK = _SINK, sink
    return prev
