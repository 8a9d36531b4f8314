"""Training state (model + optimizer + step) saved for exact resume, without pickle.

Layout of a state folder: ``state.safetensors`` (``model.<name>`` parameters and ``opt.<param_idx>.<key>``
optimizer tensors) and ``state.json`` (step, epoch position, config, optimizer param-group hyper-parameters).
Writes go to a temporary folder that is then renamed over the old one, so a kill during a save never leaves a
corrupted state: either the old or the new state is there.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file


class TrainStateError(RuntimeError):
    pass


def _flatten_optimizer(opt: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict]:
    sd = opt.state_dict()
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, dict] = {}
    for idx, st in sd["state"].items():
        for k, v in st.items():
            if isinstance(v, torch.Tensor):
                tensors[f"opt.{idx}.{k}"] = v.detach().reshape(-1).clone() if v.dim() == 0 else v.detach().clone()
                if v.dim() == 0:
                    scalars.setdefault(str(idx), {})[f"{k}__scalar"] = True
            else:
                scalars.setdefault(str(idx), {})[k] = v
    return tensors, {"param_groups": sd["param_groups"], "scalars": scalars}


def _unflatten_optimizer(tensors: dict[str, torch.Tensor], meta: dict) -> dict:
    state: dict[int, dict] = {}
    for name, t in tensors.items():
        if not name.startswith("opt."):
            continue
        _, idx, k = name.split(".", 2)
        state.setdefault(int(idx), {})[k] = t
    for idx, sc in meta["scalars"].items():
        st = state.setdefault(int(idx), {})
        for k, v in sc.items():
            if k.endswith("__scalar"):
                key = k[: -len("__scalar")]
                st[key] = st[key].reshape(())
            else:
                st[k] = v
    return {"state": state, "param_groups": meta["param_groups"]}


def save_train_state(folder: str | os.PathLike, model: torch.nn.Module, opt: torch.optim.Optimizer, info: dict) -> Path:
    """Atomically write model + optimizer + ``info`` (JSON-serialisable: step, config...) into ``folder``."""
    folder = Path(folder)
    tmp = folder.with_name(folder.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    tensors = {f"model.{k}": v.detach().contiguous().clone() for k, v in model.state_dict().items()}
    opt_tensors, opt_meta = _flatten_optimizer(opt)
    tensors.update({k: v.contiguous() for k, v in opt_tensors.items()})
    save_file(tensors, str(tmp / "state.safetensors"))
    (tmp / "state.json").write_text(json.dumps({"info": info, "optimizer": opt_meta}, indent=1))
    old = folder.with_name(folder.name + ".old")
    if folder.exists():
        if old.exists():
            shutil.rmtree(old)
        os.replace(folder, old)
    os.replace(tmp, folder)
    if old.exists():
        shutil.rmtree(old)
    return folder


def load_train_state(folder: str | os.PathLike, model: torch.nn.Module, opt: torch.optim.Optimizer | None) -> dict:
    """Restore model (strict) and optimizer from ``folder``; returns the saved ``info`` dict."""
    folder = Path(folder)
    if not (folder / "state.json").exists() and folder.with_name(folder.name + ".old").exists():
        folder = folder.with_name(folder.name + ".old")  # killed between the two renames
    try:
        meta = json.loads((folder / "state.json").read_text())
        tensors = load_file(str(folder / "state.safetensors"))
    except FileNotFoundError as exc:
        raise TrainStateError(f"{folder}: no training state to resume from ({exc.filename} missing)") from exc
    except Exception as exc:  # safetensors raises its own error types on truncation
        raise TrainStateError(f"{folder}: training state unreadable ({exc}); delete it to start over") from exc
    _load_model(folder, tensors, model)
    if opt is not None:
        opt.load_state_dict(_unflatten_optimizer(tensors, meta["optimizer"]))
    return meta["info"]


def _load_model(folder: Path, tensors: dict[str, torch.Tensor], model: torch.nn.Module) -> None:
    model_sd = {k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")}
    try:
        model.load_state_dict(model_sd, strict=True)
    except RuntimeError as exc:
        raise TrainStateError(f"{folder}: model weights do not match the configured model ({exc})") from exc


def load_state_weights(folder: str | os.PathLike, model: torch.nn.Module) -> int:
    """Only the model weights (strict) of the state in ``folder`` (``state.json`` not needed, so a state that lost it
    still exports); returns the optimizer's step count: the training step those weights are from."""
    file = Path(folder) / "state.safetensors"
    try:
        tensors = load_file(str(file))
    except FileNotFoundError as exc:
        raise TrainStateError(f"{file}: missing; the run folder needs its training state") from exc
    except Exception as exc:  # safetensors raises its own error types on truncation
        raise TrainStateError(f"{file}: training state unreadable ({exc})") from exc
    steps = {int(v.reshape(-1)[0]) for k, v in tensors.items() if k.startswith("opt.") and k.endswith(".step")}
    if len(steps) != 1:
        raise TrainStateError(f"{file}: optimizer step counts {sorted(steps)[:4]}: not one training step's state")
    _load_model(Path(folder), tensors, model)
    return steps.pop()
