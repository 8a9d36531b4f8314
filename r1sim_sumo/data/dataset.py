"""Parallel generation jobs -> dataset folders, and the default dataset recipe (train / val / test).

**Jobs.** A job (:class:`~r1sim_sumo.data.sumo_reference.SumoGenConfig` or :class:`HighwayGenJob`) has a
``key`` (sort order of the output), a ``label`` (file-safe name), ``sim_seconds`` (progress units) and
``generate(state_root, progress, stats) -> iterator of Scenario``. :func:`run_generation_jobs` runs the jobs
on a worker pool (:mod:`r1sim_sumo.workers`; by default spawned processes, one simulation each since libsumo
holds one simulation per process; ``backend="ray"`` for Ray actors on a cluster), each worker writing its
own validated shards into ``<out>/.staging/<label>/``; when every job succeeded the shards are moved into
``<out>`` in key order (deterministic whatever the completion order) and ``manifest.json`` is written last.
A job whose worker died (SUMO crash, killed process) is retried from scratch up to ``max_retries`` times.
A failing job stops everything: the error names the job (network and seed), the staging folder is removed
and no manifest is written.

**Recipe** (:class:`DatasetRecipe`, ``configs/dataset.yaml``): SUMO windows from every bundled network x
seeds, plus highway-env windows of the four envs, split by *whole simulation seeds*:

* ``train``: seeds ``0 .. train_seeds-1`` of every network except the held-out ones;
* ``val``: seeds ``10000 + i`` of the same networks (disjoint simulations: no window overlaps training);
* ``test``: seeds ``20000 + i`` of those networks *and* the held-out networks (default ``roundabout``),
  which no other split contains.

Highway-env runs are split the same way by seed. ``<out>/splits.json`` records the recipe, the networks,
envs and seeds of each split and the window counts.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from tqdm.auto import tqdm

from r1sim_sumo._memory import peak_rss_mb
from r1sim_sumo.config import from_dict
from r1sim_sumo.data.highway_reference import generate_highway_scenarios
from r1sim_sumo.data.sumo_reference import GENERATOR_VERSION as SUMO_GENERATOR_VERSION
from r1sim_sumo.data.sumo_reference import RunStats, SumoGenConfig
from r1sim_sumo.resources import list_networks, list_training_networks
from r1sim_sumo.safe_paths import safe_join
from r1sim_sumo.scenario import FORMAT_VERSION, Scenario, write_manifest, write_shard
from r1sim_sumo.workers import TaskFailedError, make_pool, report_progress
from r1sim_sumo.workers.base import DEFAULT_MAX_RETRIES

HIGHWAY_ENVS = ("highway-v0", "merge-v0", "roundabout-v0", "intersection-v0")
VAL_SEED_BASE = 10_000
TEST_SEED_BASE = 20_000
SPLITS = ("train", "val", "test")


class GenerationError(RuntimeError):
    """A generation job failed (the message names it: network/env and seed) or the output folder is taken."""


# ---------------------------------------------------------------------------- highway-env job


@dataclass
class HighwayGenJob:
    """One highway-env reference job: ``n_episodes`` episodes of ``episode_s`` [s] of ``env_name``.

    See :func:`r1sim_sumo.data.highway_reference.generate_highway_scenarios`.
    """

    env_name: str
    seed: int = 0
    n_episodes: int = 1
    episode_s: float = 40.0
    stride_steps: int = 20
    vehicles_count: int | None = None

    @property
    def key(self) -> tuple:
        return ("highway-env", self.env_name, int(self.seed))

    @property
    def label(self) -> str:
        return f"{self.env_name}__seed{int(self.seed):05d}"

    @property
    def sim_seconds(self) -> float:
        return float(self.n_episodes * self.episode_s)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def generate(self, state_root: Path | None = None, progress=None, stats: RunStats | None = None) -> Iterator[Scenario]:
        scenarios = generate_highway_scenarios(self.env_name, self.seed, n_episodes=self.n_episodes,
                                               episode_s=self.episode_s, stride_steps=self.stride_steps,
                                               vehicles_count=self.vehicles_count, progress=False)
        if stats is not None:
            stats.windows = len(scenarios)
            stats.steps = int(round(self.sim_seconds * 10))
        if progress is not None:
            progress(self.sim_seconds)
        yield from scenarios


def _describe(job) -> str:
    if isinstance(job, SumoGenConfig):
        return f"SUMO network '{job.network_name}' seed {job.seed}"
    if isinstance(job, HighwayGenJob):
        return f"highway-env '{job.env_name}' seed {job.seed}"
    return f"job '{job.label}'"


# ---------------------------------------------------------------------------- worker side


@dataclass
class JobResult:
    """What a worker reports back: its shard files (in ``job_dir``), counts and resource figures.

    ``payload`` holds the job's files (``{relative path: bytes}``) when the worker may run on another
    machine (Ray backend); the parent writes them into the staging folder.
    """

    key: tuple
    label: str
    kind: str
    config: dict
    files: list[tuple[str, int]]
    num_scenarios: int
    steps: int
    vehicle_states: int
    wall_s: float
    step_s: float
    record_s: float
    worker_peak_rss_mb: float
    extra: dict = field(default_factory=dict)
    payload: dict[str, bytes] | None = None


@dataclass
class GenTask:
    """One pool task: run ``job`` and write its shards into ``job_dir`` (or, ``inline``, return them)."""

    job: object
    job_dir: str
    shard_size: int
    inline: bool = False

    def describe(self) -> str:
        return f"{_describe(self.job)} ({self.job.label})"


def run_gen_task(task: GenTask) -> JobResult:
    """Worker entry point (any pool backend): a retried attempt starts from an empty job folder."""
    if not task.inline:
        shutil.rmtree(task.job_dir, ignore_errors=True)  # leftovers of a killed attempt
        return _run_job(task.job, task.job_dir, task.shard_size)
    with tempfile.TemporaryDirectory(prefix=f"r1sim-{task.job.label}-") as tmp:
        res = _run_job(task.job, tmp, task.shard_size)
        root = Path(tmp)
        res.payload = {str(f.relative_to(root)): f.read_bytes() for f in sorted(root.rglob("*")) if f.is_file()}
        return res


def _run_job(job, job_dir: str, shard_size: int) -> JobResult:
    """Generate the job's scenarios and write them as validated shards in ``job_dir``."""
    t0 = time.perf_counter()
    job_dir_p = Path(job_dir)
    job_dir_p.mkdir(parents=True, exist_ok=True)

    def progress(sim_s: float) -> None:
        report_progress(float(sim_s))

    stats = RunStats()
    files: list[tuple[str, int]] = []
    buf: list[Scenario] = []

    def flush() -> None:
        name = f"shard-{len(files):05d}.npz"
        write_shard(job_dir_p / name, buf)  # validates every scenario
        files.append((name, len(buf)))
        buf.clear()

    for sc in job.generate(state_root=job_dir_p, progress=progress, stats=stats):
        buf.append(sc)
        if len(buf) >= shard_size:
            flush()
    if buf:
        flush()
    return JobResult(
        key=tuple(job.key), label=job.label, kind=type(job).__name__, config=job.to_dict(), files=files,
        num_scenarios=sum(n for _, n in files), steps=stats.steps, vehicle_states=stats.vehicle_states,
        wall_s=time.perf_counter() - t0, step_s=stats.step_s, record_s=stats.record_s,
        worker_peak_rss_mb=peak_rss_mb(),
        extra={"skipped_windows": stats.skipped_windows, "demand_factor": stats.demand_factor},
    )


# ---------------------------------------------------------------------------- parent side


def check_fresh_out_dir(out_dir: str | os.PathLike) -> Path:
    """Refuse an existing non-empty folder (never overwrite a dataset)."""
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise GenerationError(f"{out}: already exists and is not empty; refusing to overwrite a dataset. "
                              "Choose a new --out folder or delete this one first.")
    return out


def execute_jobs(jobs: list, staging_dir: str | os.PathLike, workers: int = 2, shard_size: int = 256,
                 progress: bool = True, desc: str = "generate", backend: str | None = "process",
                 ray_address: str | None = None, max_retries: int = DEFAULT_MAX_RETRIES) -> list[JobResult]:
    """Run ``jobs`` on a worker pool (:mod:`r1sim_sumo.workers`), shards into ``staging_dir/<label>/``.

    :param backend: ``process`` (default: spawned processes, one simulation each), ``ray`` (actors, local or
        a cluster at ``ray_address``; shards travel back with the results) or ``local`` (this process).
    :param max_retries: a job whose worker died (SUMO crash, killed process) is re-run up to this many times.
    :return: one result per job, sorted by key (deterministic whatever the completion order).
    :raises GenerationError: naming the job (network/env and seed) that failed; the other jobs are stopped.
    """
    if not jobs:
        raise GenerationError("no generation jobs: give at least one network/env and one seed")
    labels = [j.label for j in jobs]
    dup = sorted({x for x in labels if labels.count(x) > 1})
    if dup:
        raise GenerationError(f"duplicated generation jobs {dup[:5]}: each (network, seed) may appear once")
    if shard_size < 1:
        raise GenerationError(f"shard_size must be >= 1, got {shard_size}")
    staging = Path(staging_dir)
    inline = backend == "ray"
    tasks = [GenTask(j, str(staging / j.label), shard_size, inline) for j in jobs]
    total = sum(j.sim_seconds for j in jobs)
    interactive = sys.stderr.isatty()
    bar = tqdm(total=round(total), unit="sim-s", desc=desc, disable=not progress, dynamic_ncols=interactive,
               mininterval=0.1 if interactive else 30.0)  # a log file gets a line every 30 s
    counts = {"jobs": 0, "windows": 0, "sim_s": 0.0}

    def on_progress(sim_s) -> None:
        counts["sim_s"] += float(sim_s)
        bar.update(float(sim_s))

    def on_result(i: int, res: JobResult) -> None:
        if inline:  # no progress channel from Ray actors: count the whole job now
            bar.update(jobs[i].sim_seconds)
        counts["jobs"] += 1
        counts["windows"] += res.num_scenarios
        bar.set_postfix(jobs=f"{counts['jobs']}/{len(jobs)}", windows=counts["windows"])

    try:
        with make_pool(backend or "process", max(1, min(workers, len(jobs))), ray_address=ray_address,
                       max_retries=max_retries) as pool:
            try:
                results = pool.map(run_gen_task, tasks, on_result=on_result, on_progress=on_progress)
            except TaskFailedError as exc:
                job = jobs[exc.task_id]
                raise GenerationError(f"generation job failed for {_describe(job)} ({job.label}): {exc}") from exc
            if pool.stats.retries:
                bar.write(f"[{desc}] {pool.stats.summary()}")
    finally:
        bar.close()
    for r in results:
        if r.payload is not None:  # files shipped back from a remote worker
            for rel, data in r.payload.items():
                dst = staging / r.label / rel
                dst.parent.mkdir(parents=True, exist_ok=True)
                dst.write_bytes(data)
            r.payload = None
    return sorted(results, key=lambda r: r.key)


def assemble_dataset(out_dir: str | os.PathLike, staging_dir: str | os.PathLike, results: list[JobResult],
                     extra_manifest: dict | None = None) -> Path:
    """Move the shards (and state files) of ``results`` (in this order) into ``out_dir``; write its manifest."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(staging_dir)
    shards, jobs_meta = [], []
    for r in results:
        first = len(shards)
        job_dir = safe_join(staging, r.label, "job label")  # labels come from network/env names
        for name, n in r.files:
            dst = f"shard-{len(shards):05d}.npz"
            os.replace(safe_join(job_dir, name, "shard file"), out / dst)
            shards.append({"file": dst, "num_scenarios": n})
        states = safe_join(job_dir, f"states/{r.label}", "state folder")
        if states.is_dir():
            (out / "states").mkdir(exist_ok=True)
            os.replace(states, safe_join(out / "states", r.label, "job label"))
        jobs_meta.append({"label": r.label, "kind": r.kind, "config": r.config, "num_scenarios": r.num_scenarios,
                          "first_shard": first, "num_shards": len(r.files)})
    manifest = {"format_version": FORMAT_VERSION, "shards": shards, "num_scenarios": sum(s["num_scenarios"] for s in shards),
                "jobs": jobs_meta}
    manifest.update(extra_manifest or {})
    write_manifest(out, manifest)
    return out


class _Workspace:
    """``out_dir`` checked fresh + a staging folder; on failure removes what it created (no manifest left)."""

    def __init__(self, out_dir: str | os.PathLike):
        self.out = check_fresh_out_dir(out_dir)
        self.created = not self.out.exists()
        self.out.mkdir(parents=True, exist_ok=True)
        self.staging = self.out / ".staging"

    def __enter__(self) -> _Workspace:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        shutil.rmtree(self.staging, ignore_errors=True)
        if exc_type is not None:
            if self.created:
                shutil.rmtree(self.out, ignore_errors=True)
            else:  # it existed empty: leave it empty
                for p in self.out.iterdir():
                    shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)


def run_generation_jobs(jobs: list, out_dir: str | os.PathLike, workers: int = 2, shard_size: int = 256,
                        progress: bool = True, extra_manifest: dict | None = None, backend: str | None = "process",
                        ray_address: str | None = None, max_retries: int = DEFAULT_MAX_RETRIES) -> Path:
    """Run ``jobs`` on a worker pool and write one dataset folder ``out_dir`` (shards + manifest).

    ``backend`` / ``ray_address`` / ``max_retries``: see :func:`execute_jobs`.
    """
    with _Workspace(out_dir) as ws:
        results = execute_jobs(jobs, ws.staging, workers=workers, shard_size=shard_size, progress=progress,
                               backend=backend, ray_address=ray_address, max_retries=max_retries)
        return assemble_dataset(ws.out, ws.staging, results, {"generation": _summary(results), **(extra_manifest or {})})


def _summary(results: list[JobResult]) -> dict:
    return {"num_jobs": len(results), "vehicle_states": sum(r.vehicle_states for r in results),
            "sumo_generator_version": SUMO_GENERATOR_VERSION}


# ---------------------------------------------------------------------------- the recipe


@dataclass
class DatasetRecipe:
    """The default training data: SUMO networks x seeds + highway-env envs x seeds, split by seed.

    :param networks: bundled networks to use; empty = all (``r1sim_sumo.resources.list_networks()``); training-only
        networks (``training/<name>``, :func:`r1sim_sumo.resources.list_training_networks`) only when named.
    :param heldout_networks: networks seen only by the test split.
    :param train_seeds, val_seeds, test_seeds: number of SUMO seeds per network in each split (train seeds
        ``0..n-1``, val ``10000+i``, test ``20000+i``).
    :param duration_s, warmup_s, stride_steps, demand_scale, save_states: per SUMO run (see SumoGenConfig).
    :param highway_envs: highway-env ids; empty = no highway-env data.
    :param highway_train_seeds, highway_val_seeds, highway_test_seeds: seeds per env in each split.
    :param highway_episodes, highway_episode_s: episodes per (env, seed) and their length [s].
    :param shard_size: scenarios per shard (at most; a job's last shard is smaller).
    :param slowdowns_per_vehicle_hour: random brake-hold-release events per SUMO vehicle and hour
        (:mod:`r1sim_sumo.data.slowdowns`); 0 in the default recipe.
    :param slowdown_hold_s: ``(lo, hi)`` seconds a slowed vehicle holds its low speed.
    :param depart_speed: SUMO ``departSpeed`` for every flow (``"random"``, ``"max"``, a number [m/s]); ``None``
        keeps the networks' own (``"max"`` in the bundled demand).
    :param lanechange_duration_s: SUMO ``--lanechange.duration`` [s] of every run: 0 (SUMO's default) = lane changes
        are one-step jumps of a lane width; e.g. 2.0 = continuous lateral motion over 2 s.
    :param overtake_right: every SUMO run with ``--lanechange.overtake-right true`` (passing on the right allowed,
        see :class:`~r1sim_sumo.data.sumo_reference.SumoGenConfig`); False (SUMO's default) in the default recipe.
    :param close_ups_per_vehicle_hour: random tailgate-then-reopen events per SUMO vehicle and hour
        (:mod:`r1sim_sumo.data.close_ups`); 0 in the default recipe.
    :param desired_steps_per_vehicle_hour, desired_step_factor, desired_step_hold_s: random lower-then-restore steps of
        SUMO drivers' speedFactor (:mod:`r1sim_sumo.data.desired_steps`); 0 in the default recipe.
    :param seed_offset: added to every SUMO and highway-env seed, so an add-on recipe (e.g. the recovery data)
        simulates other runs than the default recipe.
    :param policy_history: a policy (``load_policy`` name or checkpoint folder) that drives every SUMO vehicle between
        windows, so each window's history is the policy's driving and its future SUMO's recovery
        (:mod:`r1sim_sumo.data.policy_history`); ``None`` in the default recipe.
    :param policy_history_s: ``(lo, hi)`` seconds of each policy phase.
    :param policy_history_drive: ``commands`` or ``position`` (the drop-in drive of the policy phases).
    """

    networks: tuple[str, ...] = ()
    heldout_networks: tuple[str, ...] = ("roundabout",)
    train_seeds: int = 18
    val_seeds: int = 2
    test_seeds: int = 2
    duration_s: float = 600.0
    warmup_s: float = 120.0
    stride_steps: int = 20
    demand_scale: float = 1.0
    save_states: bool = False
    highway_envs: tuple[str, ...] = HIGHWAY_ENVS
    highway_train_seeds: int = 8
    highway_val_seeds: int = 1
    highway_test_seeds: int = 1
    highway_episodes: int = 2
    highway_episode_s: float = 40.0
    shard_size: int = 256
    slowdowns_per_vehicle_hour: float = 0.0
    slowdown_hold_s: tuple[float, float] = (0.0, 4.0)
    depart_speed: str | None = None
    lanechange_duration_s: float = 0.0
    overtake_right: bool = False
    close_ups_per_vehicle_hour: float = 0.0
    desired_steps_per_vehicle_hour: float = 0.0
    desired_step_factor: tuple[float, float] = (0.55, 0.9)
    desired_step_hold_s: tuple[float, float] = (4.0, 12.0)
    seed_offset: int = 0
    policy_history: str | None = None
    policy_history_s: tuple[float, float] = (4.0, 16.0)
    policy_history_drive: str = "commands"

    @classmethod
    def small(cls) -> DatasetRecipe:
        """A tiny recipe (< 1 min on 2 cores) for tests and smoke runs: 20 s recordings, 1 seed per split."""
        return cls(train_seeds=1, val_seeds=1, test_seeds=1, duration_s=20.0, warmup_s=20.0, highway_envs=("merge-v0",),
                   highway_train_seeds=1, highway_val_seeds=1, highway_test_seeds=1, highway_episodes=1,
                   highway_episode_s=11.0, shard_size=64)

    @classmethod
    def preset(cls, size: str) -> DatasetRecipe:
        if size == "small":
            return cls.small()
        if size == "default":
            return cls()
        raise ValueError(f"dataset size '{size}' unknown; choose 'small' or 'default'")

    @classmethod
    def from_dict(cls, d: dict, source: str = "dataset recipe") -> DatasetRecipe:
        """Typed construction; an unknown key or a wrong type raises ``ConfigError`` naming it."""
        return from_dict(cls, dict(d), source)

    @classmethod
    def from_yaml(cls, path: str | os.PathLike, base: DatasetRecipe | None = None) -> DatasetRecipe:
        """Load overrides from a YAML file (keys of this dataclass) over ``base`` (default recipe)."""
        p = Path(path)
        if not p.exists():
            raise FileNotFoundError(f"{p}: dataset recipe file not found")
        data = yaml.safe_load(p.read_text()) or {}
        if not isinstance(data, dict):
            raise ValueError(f"{p}: expected a mapping of recipe keys, got {type(data).__name__}")
        return cls.from_dict({**dataclasses.asdict(base or cls()), **data}, source=str(p))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    # ---- seeds and jobs
    def sumo_networks(self) -> list[str]:
        nets = list(self.networks) or list_networks()
        available = list_networks() + list_training_networks()
        missing = [n for n in [*nets, *self.heldout_networks] if n not in available]
        if missing:
            raise ValueError(f"dataset recipe: network(s) {missing} are not bundled; available: {available} "
                             "(training-only networks are named training/<name>)")
        return sorted(set(nets) | set(self.heldout_networks))

    def split_seeds(self, split: str, highway: bool = False) -> list[int]:
        n = {"train": self.highway_train_seeds if highway else self.train_seeds,
             "val": self.highway_val_seeds if highway else self.val_seeds,
             "test": self.highway_test_seeds if highway else self.test_seeds}[split]
        base = {"train": 0, "val": VAL_SEED_BASE, "test": TEST_SEED_BASE}[split]
        return [self.seed_offset + base + i for i in range(n)]

    def split_networks(self, split: str) -> list[str]:
        nets = self.sumo_networks()
        held = set(self.heldout_networks)
        seen = [n for n in nets if n not in held]
        return seen + sorted(held) if split == "test" else seen

    def jobs(self) -> dict[str, list]:
        """``{split: [SumoGenConfig | HighwayGenJob, ...]}``."""
        out: dict[str, list] = {}
        for split in SPLITS:
            jobs: list = [
                SumoGenConfig(network=n, seed=s, duration_s=self.duration_s, warmup_s=self.warmup_s,
                              stride_steps=self.stride_steps, demand_scale=self.demand_scale,
                              save_states=self.save_states, slowdowns_per_vehicle_hour=self.slowdowns_per_vehicle_hour,
                              slowdown_hold_s=self.slowdown_hold_s, depart_speed=self.depart_speed,
                              lanechange_duration_s=self.lanechange_duration_s,
                              overtake_right=self.overtake_right,
                              close_ups_per_vehicle_hour=self.close_ups_per_vehicle_hour,
                              desired_steps_per_vehicle_hour=self.desired_steps_per_vehicle_hour,
                              desired_step_factor=self.desired_step_factor,
                              desired_step_hold_s=self.desired_step_hold_s,
                              policy_history=self.policy_history, policy_history_s=self.policy_history_s,
                              policy_history_drive=self.policy_history_drive)
                for n in self.split_networks(split) for s in self.split_seeds(split)
            ]
            jobs += [HighwayGenJob(env_name=e, seed=s, n_episodes=self.highway_episodes,
                                   episode_s=self.highway_episode_s, stride_steps=self.stride_steps)
                     for e in self.highway_envs for s in self.split_seeds(split, highway=True)]
            out[split] = jobs
        return out

    def expected_sumo_windows(self, split: str = "train") -> int:
        """Upper bound of SUMO windows in ``split`` (windows without vehicles are skipped); with ``policy_history`` an
        estimate (every run counted with seed 0's phase lengths)."""
        per_run = SumoGenConfig(network="x", duration_s=self.duration_s, stride_steps=self.stride_steps,
                                policy_history=self.policy_history, policy_history_s=self.policy_history_s).num_windows()
        return per_run * len(self.split_networks(split)) * len(self.split_seeds(split))


def _split_summary(results: list[JobResult]) -> dict:
    sumo = [r for r in results if r.kind == "SumoGenConfig"]
    hw = [r for r in results if r.kind == "HighwayGenJob"]
    by_source: dict[str, int] = {}
    for r in results:
        k = f"{r.key[0]}:{r.key[1]}"
        by_source[k] = by_source.get(k, 0) + r.num_scenarios
    return {
        "num_scenarios": sum(r.num_scenarios for r in results),
        "sumo": {"networks": sorted({r.config["network"] for r in sumo}), "seeds": sorted({r.config["seed"] for r in sumo})},
        "highway": {"envs": sorted({r.config["env_name"] for r in hw}), "seeds": sorted({r.config["seed"] for r in hw})},
        "windows_by_source": dict(sorted(by_source.items())),
        "vehicle_states": sum(r.vehicle_states for r in results),
    }


def build_dataset(out_dir: str | os.PathLike, recipe: DatasetRecipe | None = None, workers: int = 2,
                  progress: bool = True, backend: str | None = "process", ray_address: str | None = None) -> Path:
    """Build ``out_dir/{train,val,test}/`` (each a dataset folder) and ``out_dir/splits.json``.

    All jobs of all splits share one process pool. Raises :class:`GenerationError` on a failing job (no
    manifest is left) and when a split ends up empty.
    """
    recipe = recipe or DatasetRecipe()
    by_split = recipe.jobs()
    split_of = {j.label: s for s, jobs in by_split.items() for j in jobs}
    all_jobs = [j for s in SPLITS for j in by_split[s]]
    t0 = time.perf_counter()
    with _Workspace(out_dir) as ws:
        results = execute_jobs(all_jobs, ws.staging, workers=workers, shard_size=recipe.shard_size, progress=progress,
                               desc="dataset", backend=backend, ray_address=ray_address)
        summary: dict = {}
        for split in SPLITS:
            rs = [r for r in results if split_of[r.label] == split]
            info = _split_summary(rs)
            if info["num_scenarios"] == 0:
                raise GenerationError(f"dataset split '{split}' has no scenarios; check the recipe's networks/seeds")
            assemble_dataset(ws.out / split, ws.staging, rs, {"split": split, "recipe": recipe.to_dict()})
            summary[split] = info
        splits = {
            "format_version": FORMAT_VERSION,
            "recipe": recipe.to_dict(),
            "heldout_networks": sorted(recipe.heldout_networks),
            "seed_bases": {s: recipe.seed_offset + b for s, b in (("train", 0), ("val", VAL_SEED_BASE), ("test", TEST_SEED_BASE))},
            "splits": summary,
            "build": {"workers": workers, "wall_s": round(time.perf_counter() - t0, 1),
                      "jobs": len(results), "sumo_generator_version": SUMO_GENERATOR_VERSION},
        }
        tmp = ws.out / "splits.json.tmp"
        tmp.write_text(json.dumps(splits, indent=2, sort_keys=True))
        os.replace(tmp, ws.out / "splits.json")
    return ws.out


def generate_sumo_dataset(configs: list[SumoGenConfig], out_dir: str | os.PathLike, workers: int = 2,
                          shard_size: int = 256, progress: bool = True, extra_manifest: dict | None = None,
                          backend: str | None = "process", ray_address: str | None = None,
                          max_retries: int = 2) -> Path:
    """Run every (network, seed) job on a worker pool and write one dataset folder (shards + manifest).

    One simulation per worker: ``backend="process"`` (spawned processes, default), ``"ray"`` (Ray actors,
    local or the cluster at ``ray_address``) or ``"local"`` (this process, one job after another); a job
    whose worker died is re-run up to ``max_retries`` times.
    Output order is sorted by (network, seed) whatever the completion order. A failing job raises
    :class:`GenerationError` naming the network and seed; no manifest is written.
    """
    return run_generation_jobs(list(configs), out_dir, workers=workers, shard_size=shard_size, progress=progress,
                               extra_manifest=extra_manifest, backend=backend, ray_address=ray_address,
                               max_retries=max_retries)
