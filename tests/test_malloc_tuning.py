"""The heap settings of the online hosts (r1sim_sumo._malloc): freed blocks are reused instead of faulted in again."""

from __future__ import annotations

import json
import platform
import subprocess
import sys

import pytest

PROBE = r"""
import json, os, resource, sys
import numpy as np
from r1sim_sumo._malloc import keep_freed_memory
applied = keep_freed_memory()
faults = []
for _ in range(20):  # a decision's temporaries: six 8 MB blocks written, all freed, allocated again
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    blocks = [np.ones(1 << 20) for _ in range(6)]
    del blocks
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
print(json.dumps({"applied": applied, "again": keep_freed_memory(), "faults": sum(faults[5:])}))
"""

glibc = pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")


def _probe(env_extra: dict) -> dict:
    import os

    env = {**os.environ, **env_extra}
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@glibc
def test_freed_blocks_are_reused_without_page_faults():
    off = _probe({"R1SIM_MALLOC_TUNING": "0"})
    on = _probe({})
    assert off["applied"] is False and on["applied"] is True and on["again"] is True
    # without the settings the freed top of the heap (48 MB, above glibc's dynamic trim threshold) goes back to the OS
    # and rounds fault pages in again (~46,000 faults over the 15 rounds counted here); with them the pages are reused
    assert off["faults"] > 15_000
    assert on["faults"] < off["faults"] / 20


def test_the_setting_is_decided_once_per_process(monkeypatch):
    from r1sim_sumo import _malloc

    monkeypatch.setattr(_malloc, "_state", {})
    monkeypatch.setenv("R1SIM_MALLOC_TUNING", "0")
    assert _malloc.keep_freed_memory() is False
    monkeypatch.setenv("R1SIM_MALLOC_TUNING", "1")
    assert _malloc.keep_freed_memory() is False  # the first call's answer stands: no half-applied settings later
