"""``import r1sim_sumo`` chooses how torch's OpenMP workers wait (before torch loads), unless the user already chose."""

import json
import os
import subprocess
import sys


def _env_after_import(**env) -> dict:
    base = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    code = ("import os, r1sim_sumo, json; "
            "print(json.dumps({k: os.environ.get(k) for k in ('OMP_WAIT_POLICY', 'GOMP_SPINCOUNT')}))")
    out = subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_passive_with_a_short_spin_by_default():
    assert _env_after_import() == {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": "10000"}


def test_a_users_choice_is_kept():
    assert _env_after_import(OMP_WAIT_POLICY="ACTIVE") == {"OMP_WAIT_POLICY": "ACTIVE", "GOMP_SPINCOUNT": None}
    assert _env_after_import(OMP_WAIT_POLICY="PASSIVE", GOMP_SPINCOUNT="0") == {"OMP_WAIT_POLICY": "PASSIVE",
                                                                                "GOMP_SPINCOUNT": "0"}
    # a spin count alone is kept too (the wait policy is still made passive)
    assert _env_after_import(GOMP_SPINCOUNT="500") == {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": "500"}
