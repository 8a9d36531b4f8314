"""Small task functions for tests, benchmarks and fault injection (importable by every worker, Ray included)."""

from __future__ import annotations

import os
import time
from pathlib import Path

from r1sim_sumo.workers.progress import report_progress


def square(x: int) -> int:
    """``x * x`` after a short sleep inversely related to ``x`` (so completion order differs from task order)."""
    time.sleep(0.02 * (x % 3))
    report_progress(1)
    return x * x


def scaled(x: int, factor: int) -> int:
    """``x * factor``: a task using the pool's ``shared`` object."""
    return x * factor


def crash_once(task: tuple[int, str]) -> dict:
    """``(value, marker_dir)``: on the first attempt of an odd ``value`` the worker process dies (``os._exit(1)``).

    The marker file ``marker_dir/attempt-<value>`` records attempts, so the retry succeeds; the result
    carries the worker's pid and the attempt number.
    """
    value, marker_dir = task
    marker = Path(marker_dir) / f"attempt-{value}"
    attempt = int(marker.read_text()) + 1 if marker.exists() else 1
    marker.write_text(str(attempt))
    if value % 2 == 1 and attempt == 1:
        os._exit(1)  # a hard crash: no exception, no cleanup (as a segfaulting simulator)
    return {"value": value, "square": value * value, "attempt": attempt, "pid": os.getpid()}


def always_crash(x: int) -> int:
    """Kills its worker every time (a task that must end in TaskFailedError)."""
    os._exit(3)


def raise_value_error(x: int) -> int:
    """Raises for ``x == 2`` (an application error that is not retried by default)."""
    if x == 2:
        raise ValueError(f"bad input {x}")
    return x
