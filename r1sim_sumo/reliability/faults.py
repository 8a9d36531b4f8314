"""Fault injection: real processes killed at random moments, numerical faults, a SUMO process dying mid-run.

* :func:`kill_and_resume` runs ``r1sim pretrain`` (or ``r1sim finetune``) on a tiny toy setup as a subprocess
  once uninterrupted, then again with ``SIGKILL`` at random moments (after the first training state exists),
  each time checking the state folder is loadable, and resumes with ``--resume`` until it finishes. The final
  weights must equal the uninterrupted run's bit for bit, and the CSV log must hold the same rows.
* :func:`nan_logits_guard` feeds NaN / +inf / all ``-inf`` logit rows to every sampler kind.
* :func:`sumo_crash_during_simulate` runs ``r1sim simulate --traci`` in a subprocess, kills its SUMO child
  process mid-run and checks the command ends with a clean error and a partial summary (no traceback).

All return plain dicts (JSON-ready) with ``passed`` and the figures; the tests and the report use them.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

from r1sim_sumo.reliability import fixtures as fx

_CLI = "from r1sim_sumo.cli import main; raise SystemExit(main())"


def _env() -> dict:
    env = dict(os.environ, R1SIM_NO_PROGRESS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    return env


def _prepare(kind: str, work: Path, steps: int) -> dict:
    """Toy data, vocabulary / initial checkpoint and a YAML config for ``kind`` (pretrain | finetune)."""

    work.mkdir(parents=True, exist_ok=True)
    data = work / "data"
    if not (data / "manifest.json").exists():
        fx.toy_dataset(data, n=8, num_agents=4)
    if kind == "pretrain":
        vocab = work / "vocab.safetensors"
        if not vocab.exists():
            fx.toy_vocab().save(vocab)
        cfg = dict(train_data=str(data), val_data=None, vocab=str(vocab), batch_size=2, max_steps=steps, warmup_steps=1,
                   lr=3e-3, eval_every=10_000, ckpt_every=2, log_every=1, threads=1,
                   model_overrides={"agent_layers": 1, "map_layers": 1})
    elif kind == "finetune":
        ck = work / "init_ckpt"
        if not (ck / "checkpoint.json").exists():
            fx.toy_checkpoint(ck, agent_layers=1, map_layers=1)
        cfg = dict(init_checkpoint=str(ck), train_data=str(data), num_rollouts=4, batch_scenes=2, sampler="topk:5",
                   num_steps=2, ppo_epochs=1, num_minibatches=1, lr=1e-3, max_iters=steps, ckpt_every=1, log_every=1,
                   threads=1)
    else:
        raise ValueError(f"kind {kind!r}: use pretrain or finetune")
    return cfg


def _cmd(kind: str, cfg_path: Path, resume: bool) -> list[str]:
    return [sys.executable, "-c", _CLI, kind, "--config", str(cfg_path), *(["--resume"] if resume else [])]


def _write_cfg(work: Path, cfg: dict, out_dir: Path, name: str) -> Path:
    import yaml

    p = work / f"{name}.yaml"
    p.write_text(yaml.safe_dump({**cfg, "out_dir": str(out_dir)}))
    return p


def _state_ok(state_dir: Path) -> str:
    """'absent', 'ok@<step>' or 'CORRUPT: ...' for a training-state folder after a kill."""
    from safetensors.torch import load_file

    if not (state_dir / "state.json").exists() and not state_dir.with_name("state.old").exists():
        return "absent"
    d = state_dir if (state_dir / "state.json").exists() else state_dir.with_name("state.old")
    try:
        info = json.loads((d / "state.json").read_text())["info"]
        load_file(str(d / "state.safetensors"))
    except Exception as exc:  # noqa: BLE001
        return f"CORRUPT: {type(exc).__name__}: {exc}"
    return f"ok@{info.get('step', info.get('iter'))}"


def _log_rows(out: Path) -> list[dict]:
    with open(out / "log.csv") as f:
        rows = list(csv.DictReader(f))
    drop = ("tokens_per_s", "wall_s", "rollout_s", "update_s", "rollouts_per_s")  # timings differ between runs
    return [{k: v for k, v in r.items() if k not in drop} for r in rows]


def _same_weights(a: Path, b: Path) -> bool:
    import torch
    from safetensors.torch import load_file

    wa, wb = load_file(str(a / "model.safetensors")), load_file(str(b / "model.safetensors"))
    return wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


def kill_and_resume(kind: str, work: str | os.PathLike, steps: int = 16, kills: int = 2, seed: int = 0,
                    timeout_s: float = 240.0) -> dict:
    """SIGKILL a real ``r1sim <kind>`` subprocess ``kills`` times at random moments, resume, compare with a clean run.

    :param kind: ``pretrain`` or ``finetune``.
    :param steps: training steps (pretrain) or iterations (finetune) of the toy run.
    :param kills: how many times the run is killed before it is allowed to finish.
    :param seed: seed of the random kill moments.
    :returns: ``{"passed", "identical_weights", "identical_log", "kills": [{"after_s", "state"}], ...}``.
    """
    rng = random.Random(seed)
    work = Path(work)
    cfg = _prepare(kind, work, steps)
    env = _env()
    t0 = time.perf_counter()
    ref_out = work / f"{kind}_ref"
    r = subprocess.run(_cmd(kind, _write_cfg(work, cfg, ref_out, "ref"), False), env=env, capture_output=True, text=True,
                       timeout=timeout_s)
    if r.returncode != 0:
        raise RuntimeError(f"reference {kind} run failed (rc {r.returncode}):\n{r.stderr[-3000:]}")
    ref_s = time.perf_counter() - t0

    out = work / f"{kind}_killed"
    cfg_path = _write_cfg(work, cfg, out, "killed")
    state_dir = out / "state"
    kill_log = []
    resume = False
    for _ in range(kills):
        p = subprocess.Popen(_cmd(kind, cfg_path, resume), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        start = time.perf_counter()
        before = _state_ok(state_dir)
        # wait until training has written (a new) state, then kill at a random moment shortly after
        while time.perf_counter() - start < timeout_s and p.poll() is None and _state_ok(state_dir) == before:
            time.sleep(0.02)
        time.sleep(rng.uniform(0.0, 0.6))
        finished = p.poll() is not None
        if not finished:
            p.send_signal(signal.SIGKILL)
        p.wait(timeout=30)
        err = p.stderr.read() if p.stderr else ""
        if finished and p.returncode != 0:
            raise RuntimeError(f"{kind} run failed before the kill (rc {p.returncode}):\n{err[-3000:]}")
        kill_log.append({"after_s": round(time.perf_counter() - start, 2), "killed": not finished, "state": _state_ok(state_dir)})
        resume = True
    r = subprocess.run(_cmd(kind, cfg_path, True), env=env, capture_output=True, text=True, timeout=timeout_s)
    if r.returncode != 0:
        raise RuntimeError(f"resumed {kind} run failed (rc {r.returncode}):\n{r.stderr[-3000:]}")
    same_w = _same_weights(ref_out / "final", out / "final")
    same_log = _log_rows(ref_out) == _log_rows(out)
    corrupt = [k for k in kill_log if k["state"].startswith("CORRUPT")]
    return {"kind": kind, "steps": steps, "kills": kill_log, "identical_weights": same_w, "identical_log": same_log,
            "state_never_corrupt": not corrupt, "reference_run_s": round(ref_s, 1),
            "passed": bool(same_w and same_log and not corrupt and any(k["killed"] for k in kill_log))}


class _Collect(logging.Handler):
    def __init__(self, level: int):
        super().__init__(level)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def nan_logits_guard() -> dict:
    """NaN / +inf / all ``-inf`` rows: every sampler falls back to token 0 for those rows and warns; others unaffected."""
    import warnings

    import torch

    from r1sim_sumo.rollout.samplers import parse_sampler

    logits = torch.randn(5, 64)
    logits[0, 3] = float("nan")
    logits[1, :] = float("-inf")
    logits[2, 7] = float("inf")
    logits[3, :] = float("nan")
    rows = {}
    for spec in ("greedy", "topk:5", "topk:1000", "entropy:16,80", "entropy-norm:16,80", "full", "topk:5@0.5"):
        h = _Collect(level=logging.WARNING)
        records = h.records
        logging.getLogger("r1sim_sumo.rollout.samplers").addHandler(h)
        try:
            with warnings.catch_warnings(record=True) as w:
                warnings.simplefilter("always")
                out = parse_sampler(spec)(logits, torch.Generator().manual_seed(0))
        finally:
            logging.getLogger("r1sim_sumo.rollout.samplers").removeHandler(h)
        warned = bool(records) or any("fall back" in str(x.message) or "NaN" in str(x.message) for x in w)
        tok = out.token.tolist()
        finite = bool(torch.isfinite(out.logp).all() and torch.isfinite(out.entropy).all())
        ok = tok[:4] == [0, 0, 0, 0] and 0 <= tok[4] < 64 and finite and warned
        rows[spec] = {"tokens": tok, "finite_logp_entropy": finite, "warned": warned, "passed": ok}
    return {"samplers": rows, "passed": all(r["passed"] for r in rows.values())}


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == pid:
            out.append(int(d.name))
    return out


def sumo_crash_during_simulate(work: str | os.PathLike, kill_after_s: float = 4.0, timeout_s: float = 180.0) -> dict:
    """``r1sim simulate --traci --untrained`` in a subprocess; its SUMO child is SIGKILLed after ``kill_after_s`` of
    simulation progress. Passes when the command exits with code 3, prints a one-line error and a partial summary
    and no Python traceback."""
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    js = work / "partial.json"
    cmd = [sys.executable, "-c", _CLI, "simulate", "--traci", "--untrained", "--end", "600", "--no-progress", "--json", str(js)]
    p = subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    start = time.perf_counter()
    sumo_pid = None
    while time.perf_counter() - start < timeout_s and p.poll() is None:
        kids = [k for k in _children(p.pid) if "sumo" in Path(f"/proc/{k}/comm").read_text(errors="ignore")] if p.poll() is None else []
        if kids:
            sumo_pid = kids[0]
            break
        time.sleep(0.05)
    if sumo_pid is None:
        p.kill()
        p.communicate()
        raise RuntimeError("no SUMO child process appeared")
    time.sleep(kill_after_s)
    os.kill(sumo_pid, signal.SIGKILL)
    try:
        stdout, stderr = p.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        p.kill()
        stdout, stderr = p.communicate()
    summary = json.loads(js.read_text()) if js.exists() else {}
    no_tb = "Traceback" not in stderr
    err_line = next((ln for ln in stderr.splitlines() if ln.startswith("r1sim simulate: error:")), "")
    passed = p.returncode == 3 and no_tb and bool(err_line) and "departed" in stdout and bool(summary.get("sumo_crashed"))
    return {"returncode": p.returncode, "error_line": err_line, "traceback": not no_tb,
            "partial_sim_s": summary.get("sim_seconds"), "departed": summary.get("departed"),
            "balanced": summary.get("balanced"), "stdout_tail": stdout[-1500:], "passed": passed}
