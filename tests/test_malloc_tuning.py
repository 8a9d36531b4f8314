"""The heap settings of training and the online hosts (r1sim_sumo._memory.keep_freed_memory): freed blocks are reused
instead of faulted in again, and R1SIM_MALLOC_TUNING=0 leaves the allocator alone."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

PROBE = r"""
import json, resource
import numpy as np
from r1sim_sumo._memory import keep_freed_memory
applied = keep_freed_memory()
faults = []
for _ in range(20):  # a decision's temporaries: six 8 MB blocks written, all freed, allocated again
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    blocks = [np.ones(1 << 20) for _ in range(6)]
    del blocks
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
print(json.dumps({"applied": applied, "faults": sum(faults[5:])}))
"""

glibc = pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")


def _probe(env_extra: dict) -> dict:
    env = {**os.environ, **env_extra}
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@glibc
def test_freed_blocks_are_reused_without_page_faults():
    off = _probe({"R1SIM_MALLOC_TUNING": "0"})
    on = _probe({"R1SIM_MALLOC_TUNING": "1"})
    assert off["applied"] is False and on["applied"] is True
    # without the settings the freed top of the heap (48 MB, above glibc's dynamic trim threshold) goes back to the OS
    # and rounds fault pages in again (~46,000 faults over the 15 rounds counted here); with them the pages are reused
    assert off["faults"] > 15_000
    assert on["faults"] < off["faults"] / 20


def test_every_policy_driver_asks_for_the_settings(monkeypatch):
    import numpy as np

    import r1sim_sumo
    from r1sim_sumo.scenario import MapPolylines
    from r1sim_sumo.sim import policy_driver

    calls = []
    monkeypatch.setattr(policy_driver, "keep_freed_memory", lambda: calls.append(1) or True)
    xs = np.linspace(0, 300, 61)
    road = MapPolylines.from_lists([np.stack([xs, np.zeros_like(xs)], -1)], [0], ["l0"], [30], [3.5])
    policy_driver.PolicyDriver(r1sim_sumo.load_policy(), road)
    assert calls == [1]
