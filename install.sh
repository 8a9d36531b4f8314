#!/usr/bin/env bash
# Install r1sim-sumo (editable, with dev extras) on a fresh machine.
# A bare `torch` requirement would pull a multi-GB CUDA build, so the CPU build torch==2.13.0 goes in first
# when no torch is present. SUMO comes from PyPI (eclipse-sumo, libsumo): no system SUMO needed.
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3}
if ! "$PY" -c "import torch" >/dev/null 2>&1; then
  "$PY" -m pip install "torch==2.13.0"
fi
"$PY" -m pip install -e ".[dev]"
"$PY" -c "import r1sim_sumo, libsumo, highway_env; from r1sim_sumo._sumo_env import ensure_sumo_home; print('r1sim-sumo', r1sim_sumo.__version__, 'SUMO_HOME', ensure_sumo_home())"
