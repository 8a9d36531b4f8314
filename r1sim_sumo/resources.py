"""Find bundled files (networks, configs, checkpoints) whether installed as a wheel or run from a checkout.

Bundled networks live in the top-level ``networks/`` of the repository; the wheel force-includes them as
``r1sim_sumo/_bundled/networks``. Never resolved relative to the working directory.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

_PKG_DIR = Path(str(resources.files("r1sim_sumo")))
_REPO_DIR = _PKG_DIR.parent


def _bundled(name: str) -> Path:
    for cand in (_PKG_DIR / "_bundled" / name, _REPO_DIR / name):
        if cand.is_dir():
            return cand
    raise FileNotFoundError(f"bundled folder '{name}' not found in {_PKG_DIR / '_bundled'} nor {_REPO_DIR}")


def networks_dir() -> Path:
    return _bundled("networks")


def configs_dir() -> Path:
    return _bundled("configs")


def checkpoints_dir() -> Path:
    return _PKG_DIR / "checkpoints"


def list_networks() -> list[str]:
    """Names of the bundled SUMO networks (folders of ``networks/`` holding a ``.sumocfg``)."""
    root = networks_dir()
    return sorted(p.name for p in root.iterdir() if p.is_dir() and any(p.glob("*.sumocfg")))


def list_training_networks() -> list[str]:
    """Names (``training/<name>``) of the training-only SUMO networks of ``networks/training/``: extra geometry for
    dataset recipes (e.g. roundabouts other than the held-out one), not part of the bundled five that envs, the
    drop-in report and the default recipe use. :func:`network_files` takes these names too."""
    root = networks_dir() / "training"
    if not root.is_dir():
        return []
    return sorted(f"training/{p.name}" for p in root.iterdir() if p.is_dir() and any(p.glob("*.sumocfg")))


def network_path(name: str) -> Path:
    """Folder of bundled network ``name``; raises with the list of valid names otherwise."""
    p = networks_dir() / name
    if not p.is_dir():
        raise FileNotFoundError(f"unknown bundled network '{name}'; choose one of {list_networks() + list_training_networks()}")
    return p


def network_files(name: str) -> dict[str, Path]:
    """``{'net': *.net.xml, 'sumocfg': *.sumocfg}`` for bundled network ``name``."""
    p = network_path(name)
    nets = sorted(p.glob("*.net.xml"))
    cfgs = sorted(p.glob("*.sumocfg"))
    if not nets or not cfgs:
        raise FileNotFoundError(f"network folder {p} lacks a .net.xml or .sumocfg (rebuild: python networks/build.py)")
    return {"net": nets[0], "sumocfg": cfgs[0]}
