"""Locate SUMO from the PyPI ``eclipse-sumo`` wheel so no system SUMO is needed.

``ensure_sumo_home()`` sets ``SUMO_HOME`` from ``sumo.SUMO_HOME`` when it is unset and returns it;
``sumo_binary(name)`` returns the path of a SUMO tool (``sumo``, ``netconvert``, ``sumo-gui``...).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path


class SumoNotFoundError(RuntimeError):
    pass


def ensure_sumo_home() -> Path:
    """Return SUMO_HOME, setting it from the installed ``sumo`` package (eclipse-sumo) when unset."""
    home = os.environ.get("SUMO_HOME")
    if home and Path(home).is_dir():
        return Path(home)
    try:
        import sumo  # eclipse-sumo wheel
    except ImportError as exc:  # pragma: no cover - install problem
        raise SumoNotFoundError(
            "SUMO_HOME is unset and the 'eclipse-sumo' package is not installed: run `pip install eclipse-sumo`"
        ) from exc
    os.environ["SUMO_HOME"] = str(sumo.SUMO_HOME)
    return Path(sumo.SUMO_HOME)


def sumo_binary(name: str = "sumo") -> str:
    """Absolute path of a SUMO executable shipped by eclipse-sumo (falls back to PATH)."""
    home = ensure_sumo_home()
    for cand in (home / "bin" / name, home / "bin" / f"{name}.exe"):
        if cand.exists():
            return str(cand)
    found = shutil.which(name)
    if found:
        return found
    raise SumoNotFoundError(f"SUMO executable '{name}' not found under {home}/bin nor on PATH")


def sumo_tools_dir() -> Path:
    return ensure_sumo_home() / "tools"
