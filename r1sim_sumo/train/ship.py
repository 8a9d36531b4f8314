"""Ship a trained checkpoint as one of the package's bundled policies (``r1sim_sumo/checkpoints/<name>/``).

    python -m r1sim_sumo.train.ship runs/rings_more/ckpt-000800 --name r1sim-nano
    python -m r1sim_sumo.train.ship runs/grpo_c/ckpt-000030 --name r1sim-grpo

The weights are copied unchanged (same SHA-256, so :func:`~r1sim_sumo.model.checkpoint.load_checkpoint` accepts
them). ``checkpoint.json`` keeps the model config and vocabulary and gains the whole training **lineage**: every
run the weights went through, found by following ``init_checkpoint`` back from the shipped checkpoint (a
pretraining checkpoint records it in ``checkpoint.json``; a fine-tune in its run's ``config.yaml``) down to the
previously shipped policy, whose own recorded segments are kept. Each lineage entry names the checkpoint, the
run's config file, and its steps (pretraining) or iterations (fine-tuning) and CPU hours where recorded, so the
shipped weights can be reproduced command by command (docs/training/README.md).

The old ``MODEL_CARD.md`` / ``model_card.json`` / ``train_log.csv`` of the bundled folder are replaced (the card
describes other weights); the previous files stay in git history. Regenerate the card afterwards with the command
this prints (``r1sim_sumo.train.model_card``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import yaml

from r1sim_sumo.model.checkpoint import BUNDLED_DIR, META_FILE, WEIGHTS_FILE, CheckpointError, load_checkpoint

CARD_FILES = ("MODEL_CARD.md", "model_card.json", "train_log.csv")


def _meta(ckpt: Path) -> dict:
    return json.loads((ckpt / META_FILE).read_text())


def _resolve(ref: str, bundled_dir: Path) -> Path:
    """A lineage reference: a bundled name (``r1sim-nano``) or a path."""
    p = Path(ref)
    return p if p.exists() or "/" in ref else bundled_dir / ref


def lineage(ckpt: str | Path, bundled_dir: Path = BUNDLED_DIR, max_depth: int = 64) -> list[dict]:
    """The runs behind ``ckpt``, oldest first. Each entry: ``checkpoint`` (path as recorded), ``kind``
    (``pretrain`` | ``finetune`` | ``shipped``), ``config`` (the run's config.yaml when it exists), ``steps`` or
    ``iters``, ``method`` (fine-tunes), ``cpu_hours`` (when recorded) and ``init_checkpoint``. A bundled
    checkpoint ends the walk and contributes its recorded ``segments`` (or its own entry)."""
    out: list[dict] = []
    ref, seen = str(ckpt), set()
    for _ in range(max_depth):
        path = _resolve(ref, bundled_dir)
        if not (path / META_FILE).exists():
            out.append({"checkpoint": ref, "kind": "missing", "note": f"{path / META_FILE} not found; lineage ends here"})
            break
        key = str(path.resolve())
        if key in seen:
            raise CheckpointError(f"{path}: init_checkpoint chain loops back to itself")
        seen.add(key)
        tr = _meta(path).get("training", {})
        if path.resolve().parent == bundled_dir.resolve():
            own = tr.get("train") or tr.get("finetune") or {}
            shipped = (tr.get("lineage") or own.get("lineage") or own.get("segments")
                       or [{"what": "see its MODEL_CARD.md"}])  # ship() keeps the lineage under training.train
            out.append({"checkpoint": ref, "kind": "shipped", "segments": shipped})
            break
        cfg_path = path.parent / "config.yaml"
        run_cfg = yaml.safe_load(cfg_path.read_text()) if cfg_path.exists() else {}
        if "train" in tr:
            t = tr["train"]
            entry = {"checkpoint": ref, "kind": "pretrain", "steps": t.get("steps"), "cpu_hours": t.get("cpu_hours"),
                     "agent_tokens_seen": t.get("agent_tokens_seen"), "init_checkpoint": t.get("init_checkpoint")}
        elif "finetune" in tr:
            t = tr["finetune"]
            entry = {"checkpoint": ref, "kind": "finetune", "method": t.get("method"), "iters": t.get("iters"),
                     "init_checkpoint": run_cfg.get("init_checkpoint")}
        else:
            raise CheckpointError(f"{path / META_FILE}: field 'training' has neither 'train' nor 'finetune'; cannot follow its lineage")
        if cfg_path.exists():
            entry["config"] = str(cfg_path)
            entry["run_config"] = run_cfg  # inline: the run's folder is not shipped
        out.append(entry)
        if not entry.get("init_checkpoint"):
            break
        ref = str(entry["init_checkpoint"])
    else:
        raise CheckpointError(f"{ckpt}: lineage deeper than {max_depth} runs")
    return out[::-1]


def flat_runs(chain: list[dict]) -> list[dict]:
    """Every pretraining / fine-tuning run of a lineage, oldest first, including those recorded inside the shipped
    policies it starts from (their ``segments``)."""
    out = []
    for e in chain:
        if e.get("kind") == "shipped":
            out += flat_runs([s for s in e.get("segments", []) if isinstance(s, dict)])
        elif e.get("kind") in ("pretrain", "finetune"):
            out.append(e)
    return out


def ship(src: str | Path, name: str, bundled_dir: Path = BUNDLED_DIR) -> Path:
    """Copy checkpoint ``src`` to ``bundled_dir/name`` with its lineage in ``checkpoint.json``; returns the folder.
    Refuses (``CheckpointError``) a checkpoint that does not load."""
    src = Path(src)
    load_checkpoint(src)  # refuse broken weights before touching the bundled folder
    meta = _meta(src)
    chain = lineage(src, bundled_dir)
    tr = meta.get("training", {})
    kind = "finetune" if "finetune" in tr and "train" not in tr else "train"
    info = dict(tr.get(kind, {}))
    info["shipped_from"] = str(src)
    info["lineage"] = chain
    cpu = [e["cpu_hours"] for e in flat_runs(chain) if isinstance(e.get("cpu_hours"), (int, float))]
    if cpu:
        info["cpu_hours_recorded_total"] = round(float(sum(cpu)), 3)
    meta["training"] = {kind: info}
    dest = bundled_dir / name
    with tempfile.TemporaryDirectory(dir=bundled_dir) as tmp:
        stage = Path(tmp) / name
        stage.mkdir()
        shutil.copy2(src / WEIGHTS_FILE, stage / WEIGHTS_FILE)
        (stage / META_FILE).write_text(json.dumps(meta, indent=2, sort_keys=True, default=str))
        run_log = src.parent / "log.csv"
        if run_log.exists():
            shutil.copy2(run_log, stage / "train_log.csv")
        run_cfg = src.parent / "config.yaml"
        if kind == "finetune" and run_cfg.exists():
            shutil.copy2(run_cfg, stage / "finetune_config.yaml")
        load_checkpoint(stage)  # the staged copy must load before it replaces anything
        if dest.exists():
            for f in (WEIGHTS_FILE, META_FILE, "finetune_config.yaml", *CARD_FILES):
                (dest / f).unlink(missing_ok=True)
        dest.mkdir(exist_ok=True)
        for f in stage.iterdir():
            shutil.move(str(f), dest / f.name)
    return dest


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint", help="checkpoint directory to ship (e.g. runs/rings_more/ckpt-000800)")
    ap.add_argument("--name", required=True, help="bundled name (r1sim-nano, r1sim-grpo)")
    args = ap.parse_args(argv)
    try:
        dest = ship(args.checkpoint, args.name)
    except CheckpointError as exc:
        raise SystemExit(f"ship: {exc}") from None
    for e in _meta(dest)["training"].popitem()[1]["lineage"]:
        print(f"  {e['kind']:9s} {e['checkpoint']}  " + "  ".join(f"{k}={e[k]}" for k in ("steps", "iters", "method", "cpu_hours") if e.get(k) is not None))
    try:
        dest = dest.relative_to(Path.cwd())
    except ValueError:
        pass
    print(f"shipped {args.checkpoint} as {dest}; now regenerate its card:\n"
          f"  python -m r1sim_sumo.train.model_card {dest} --train data/generated/default/train --heldout data/generated/default/val "
          f"--closed-loop data/generated/default/test --max-heldout 400 --max-closed-loop 40 --rollouts 8 --sampler topk:5 --threads 1")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
