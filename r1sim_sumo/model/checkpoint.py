"""Policy checkpoints: a directory with ``model.safetensors`` (weights under ``model.``, the motion vocabulary
under ``vocab.``) and ``checkpoint.json`` (model config, vocabulary fingerprint, package version, training
info, size and SHA-256 of the weights file). Loading never unpickles and is strict; every refusal raises
:class:`CheckpointError` naming the file and the fix.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import torch

from r1sim_sumo._version import __version__
from r1sim_sumo.config import ConfigError
from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.policy import TrafficPolicy

FORMAT = "r1sim-policy"
FORMAT_VERSION = 1
WEIGHTS_FILE = "model.safetensors"
META_FILE = "checkpoint.json"
MODEL_PREFIX = "model."
VOCAB_PREFIX = "vocab."
DEFAULT_CHECKPOINT = "r1sim-nano"
BUNDLED_DIR = Path(__file__).resolve().parent.parent / "checkpoints"


class CheckpointError(ValueError):
    """A checkpoint cannot be used; the message names the file and the fix."""


@dataclass
class Policy:
    """A loaded policy: the model (eval mode) with its vocabulary and the checkpoint's metadata."""

    model: TrafficPolicy
    vocab: object  # r1sim_sumo.tokens.MotionVocab
    config: PolicyConfig
    info: dict = field(default_factory=dict)  # checkpoint.json contents
    path: Path | None = None


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _major_minor(version: str) -> tuple[int, ...]:
    return tuple(int(p) for p in str(version).split(".")[:2])


def save_checkpoint(directory: str | os.PathLike, model: TrafficPolicy, vocab, extra: dict | None = None) -> Path:
    """Write ``directory/model.safetensors`` and ``directory/checkpoint.json``; returns the directory.

    :param vocab: the :class:`r1sim_sumo.tokens.MotionVocab` the model was trained with (its ``sizes`` must
        equal the model's ``vocab_sizes``).
    :param extra: JSON-serialisable training information (steps, data, metrics, ...).
    """
    from safetensors.torch import save_file

    cfg = model.config
    if tuple(vocab.sizes) != tuple(cfg.vocab_sizes):
        raise CheckpointError(f"vocabulary sizes {tuple(vocab.sizes)} differ from the model's vocab_sizes {cfg.vocab_sizes}")
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    tensors = {MODEL_PREFIX + k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    tensors.update({k: v.contiguous() for k, v in vocab.to_dict(prefix=VOCAB_PREFIX).items()})
    weights = d / WEIGHTS_FILE
    tmp = weights.with_name(weights.name + ".tmp")
    save_file(tensors, str(tmp), metadata={"format": FORMAT})
    os.replace(tmp, weights)
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "package_version": __version__,
        "model_config": cfg.to_dict(),
        "num_parameters": model.num_parameters(),
        "vocab_fingerprint": vocab.fingerprint(),
        "vocab_sizes": list(vocab.sizes),
        "weights": {"file": WEIGHTS_FILE, "bytes": weights.stat().st_size, "sha256": _sha256(weights)},
        "training": dict(extra or {}),
    }
    (d / META_FILE).write_text(json.dumps(meta, indent=2, sort_keys=True, default=str))
    return d


def load_checkpoint(
    directory: str | os.PathLike, device: str | torch.device = "cpu", expected_vocab_fingerprint: str | None = None
) -> Policy:
    """Load a checkpoint directory written by :func:`save_checkpoint` (safetensors only, ``strict=True``).

    Refuses, with :class:`CheckpointError`: a missing/unreadable ``checkpoint.json``, another format or an
    incompatible package major.minor version, a truncated or modified weights file, a non-safetensors file,
    a missing or different vocabulary fingerprint, and weights whose names or shapes do not fit the config.
    """
    from safetensors.torch import load_file

    from r1sim_sumo.tokens import MotionVocab

    d = Path(directory)
    meta_path, weights = d / META_FILE, d / WEIGHTS_FILE
    if not d.is_dir():
        raise CheckpointError(f"{d}: checkpoint directory not found (pass a directory holding {META_FILE} and {WEIGHTS_FILE})")
    if not meta_path.exists():
        raise CheckpointError(f"{meta_path}: missing; a checkpoint directory needs {META_FILE} (write it with save_checkpoint)")
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{meta_path}: not valid JSON ({exc}); re-save the checkpoint") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(f"{meta_path}: field 'format' is {meta.get('format') if isinstance(meta, dict) else None!r}, expected {FORMAT!r}")
    saved_v, ours = meta.get("package_version", "?"), __version__
    try:
        compatible = _major_minor(saved_v) == _major_minor(ours)
    except ValueError:
        compatible = False
    if not compatible:
        raise CheckpointError(
            f"{meta_path}: written by r1sim_sumo {saved_v}, this is {ours} (major.minor must match); "
            f"install r1sim-sumo=={saved_v} or retrain/convert the checkpoint"
        )
    if not weights.exists():
        raise CheckpointError(f"{weights}: missing; copy the whole checkpoint directory")
    expect = meta.get("weights", {})
    size = weights.stat().st_size
    if "bytes" in expect and size != expect["bytes"]:
        raise CheckpointError(f"{weights}: {size} bytes but {META_FILE} records {expect['bytes']}; the file is truncated or replaced, copy it again")
    if "sha256" in expect and _sha256(weights) != expect["sha256"]:
        raise CheckpointError(f"{weights}: SHA-256 differs from the one in {META_FILE}; the file is corrupted or replaced, copy it again")
    try:
        tensors = load_file(str(weights), device="cpu")
    except Exception as exc:  # safetensors raises its own error types for bad headers
        raise CheckpointError(f"{weights}: not a readable safetensors file ({type(exc).__name__}: {exc}); pickled .pt files are not accepted") from exc
    fp = meta.get("vocab_fingerprint")
    if not fp:
        raise CheckpointError(f"{meta_path}: field 'vocab_fingerprint' missing; re-save the checkpoint with its vocabulary")
    try:
        vocab = MotionVocab.from_dict({k: v for k, v in tensors.items() if k.startswith(VOCAB_PREFIX)}, prefix=VOCAB_PREFIX, source=str(weights))
    except ValueError as exc:
        raise CheckpointError(f"{weights}: vocabulary tensors unusable ({exc}); re-save the checkpoint with its vocabulary") from exc
    if vocab.fingerprint() != fp:
        raise CheckpointError(f"{meta_path}: vocab_fingerprint {fp} differs from the stored vocabulary's {vocab.fingerprint()}; the files do not belong together")
    if expected_vocab_fingerprint is not None and fp != expected_vocab_fingerprint:
        raise CheckpointError(
            f"{d}: trained with vocabulary {fp}, but vocabulary {expected_vocab_fingerprint} was requested; "
            "tokenize with the checkpoint's vocabulary (Policy.vocab) or load a matching checkpoint"
        )
    try:
        cfg = PolicyConfig.from_dict(meta.get("model_config", {}), f"{meta_path}: model_config")
    except ConfigError as exc:
        raise CheckpointError(f"{exc}; this r1sim_sumo cannot build that model") from exc
    try:
        model = TrafficPolicy(cfg, [torch.from_numpy(vocab.traj[t]) for t in range(cfg.num_agent_types)])
    except ValueError as exc:
        raise CheckpointError(f"{meta_path}: model_config does not fit the stored vocabulary ({exc})") from exc
    state = {k[len(MODEL_PREFIX):]: v for k, v in tensors.items() if k.startswith(MODEL_PREFIX)}
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise CheckpointError(f"{weights}: weights do not fit model_config in {META_FILE} ({exc}); the files do not belong together") from exc
    model.to(device).eval()
    return Policy(model=model, vocab=vocab, config=cfg, info=meta, path=d)


def bundled_checkpoints() -> list[str]:
    """Names of the checkpoints shipped in ``r1sim_sumo/checkpoints/``."""
    if not BUNDLED_DIR.is_dir():
        return []
    return sorted(p.name for p in BUNDLED_DIR.iterdir() if (p / META_FILE).exists())


def load_policy(name_or_path: str | os.PathLike | None = None, device: str | torch.device = "cpu") -> Policy:
    """``None`` -> the shipped default (``r1sim-nano``), a bundled name, or a checkpoint directory path."""
    name = DEFAULT_CHECKPOINT if name_or_path is None else name_or_path
    p = Path(name)
    if p.is_dir():
        return load_checkpoint(p, device=device)
    bundled = BUNDLED_DIR / str(name)
    if (bundled / META_FILE).exists():
        return load_checkpoint(bundled, device=device)
    raise FileNotFoundError(
        f"no checkpoint directory {p} and no bundled checkpoint {str(name)!r} in {BUNDLED_DIR} "
        f"(bundled: {bundled_checkpoints() or 'none yet'}); train one with `r1sim pretrain` or pass a checkpoint directory"
    )
