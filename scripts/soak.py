#!/usr/bin/env python3
"""Soak test (not part of the default test command): a long SUMO run with the shipped policy driving every vehicle.

    python scripts/soak.py --sim-seconds 3600 --out docs/reliability/soak     # the full hour (300 s took 41 s wall here: about 8 min)
    python scripts/soak.py --sim-seconds 300 --out /tmp/soak                   # a short one

Same as ``python -m r1sim_sumo.reliability soak``; see r1sim_sumo/reliability/soak.py for what is checked.
"""

import argparse
import sys

from r1sim_sumo.reliability.__main__ import add_soak_arguments, run_soak_cli

if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_soak_arguments(p)
    sys.exit(run_soak_cli(p.parse_args()))
