"""Worker pools: ordered results, retries after a killed worker, and backends that agree with the in-process run
(SUMO generation, policy evaluation, batch simulation), on spawned processes and on a local Ray cluster.

The Ray tests (``pytest -m ray``, ~25 s of which Ray start-up ~10 s) run in the default command (Ray is in the dev
extra); they skip with a message when Ray is not installed."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from test_evaluate import curved_scene

from r1sim_sumo.data.dataset import run_generation_jobs
from r1sim_sumo.data.sumo_reference import SumoGenConfig
from r1sim_sumo.evaluate import evaluate_policy
from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.workers import TaskFailedError, make_pool
from r1sim_sumo.workers.testing import always_crash, crash_once, raise_value_error, scaled, square


@pytest.fixture(scope="module")
def process_pool():
    with make_pool("process", workers=2) as pool:
        yield pool


@pytest.fixture(scope="module")
def ray_pool():
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install 'ray>=2.9'); Ray backend tests skipped")
    ray.init(num_cpus=4, include_dashboard=False, log_to_driver=False)  # 4 logical CPUs: room for a second pool
    try:
        with make_pool("ray", workers=2) as pool:
            yield pool
    finally:
        ray.shutdown()


def _same_rows(a: list[dict], b: list[dict]) -> bool:
    """Per-scenario metric rows equal, NaN == NaN."""
    def eq(x, y):
        return x == y or (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y))
    return len(a) == len(b) and all(ra.keys() == rb.keys() and all(eq(ra[k], rb[k]) for k in ra) for ra, rb in zip(a, b, strict=True))


def _check_ordered_and_crash_survived(pool, tmp_path) -> None:
    progress: list = []
    assert pool.map(square, range(7), on_progress=progress.append) == [x * x for x in range(7)]
    assert pool.map(scaled, range(5), shared=3) == [0, 3, 6, 9, 12]
    before = pool.stats.retries
    out = pool.map(crash_once, [(v, str(tmp_path)) for v in range(6)])
    assert [r["value"] for r in out] == list(range(6))  # every task once, in task order
    assert [r["attempt"] for r in out] == [1, 2, 1, 2, 1, 2]  # odd tasks died on attempt 1, retried once
    assert pool.stats.retries - before == 3
    assert {f["task_id"] for f in pool.stats.failures if f["cause"] == "died"} >= {1, 3, 5}
    if pool.backend == "process":
        assert progress == [1] * 7


# ---------------------------------------------------------------------------- pool semantics


def test_process_pool_order_and_killed_worker_retried(process_pool, tmp_path):
    _check_ordered_and_crash_survived(process_pool, tmp_path)
    with pytest.raises(TaskFailedError, match=r"task 0 \(5\): its worker died on each of 3 attempt") as err:
        process_pool.map(always_crash, [5])
    assert err.value.cause == "died" and err.value.attempts == 3
    assert process_pool.map(square, [4]) == [16]  # the pool still works after the failure


def test_task_exception_named_and_not_retried_by_default():
    with make_pool("local") as pool:
        with pytest.raises(TaskFailedError, match=r"task 2 \(2\) raised ValueError: bad input 2") as err:
            pool.map(raise_value_error, range(4))
        assert err.value.cause == "raised" and pool.stats.retries == 0
    with make_pool("local", retry_exceptions=True, max_retries=1) as pool:
        with pytest.raises(TaskFailedError):
            pool.map(raise_value_error, [2])
        assert pool.stats.retries == 1
    with pytest.raises(ValueError, match="backend 'threads' unknown"):
        make_pool("threads", 2)


# ---------------------------------------------------------------------------- same results as in-process


def _tiny_jobs() -> list[SumoGenConfig]:
    return [SumoGenConfig(network="motorway_merge", seed=s, duration_s=10.0, warmup_s=5.0, stride_steps=5) for s in (1, 0)]


def _same_dataset(a, b) -> None:
    da, db = ScenarioDataset(a), ScenarioDataset(b)
    assert len(da) == len(db) > 0
    for sa, sb in zip(da, db, strict=True):
        assert sa.metadata == sb.metadata
        for f in ("x_m", "y_m", "yaw_rad", "speed_mps", "valid"):
            assert np.array_equal(getattr(sa.agents, f), getattr(sb.agents, f)), f
        assert list(sa.agents.ids) == list(sb.agents.ids)


@pytest.fixture(scope="module")
def local_generation(tmp_path_factory):
    return run_generation_jobs(_tiny_jobs(), tmp_path_factory.mktemp("gen") / "local", backend="local", progress=False)


@pytest.fixture(scope="module")
def local_eval(policy):
    scs = [curved_scene(s) for s in range(3)]
    return scs, evaluate_policy(policy, scs, "topk:5", num_rollouts=2, seed=3, batch_scenes=1, progress=False)


@pytest.mark.sumo
def test_process_generation_equals_in_process(local_generation, tmp_path):
    out = run_generation_jobs(_tiny_jobs(), tmp_path / "proc", workers=2, backend="process", progress=False)
    _same_dataset(local_generation, out)
    labels = [j["label"] for j in json.loads((out / "manifest.json").read_text())["jobs"]]
    assert labels == ["motorway_merge__seed00000", "motorway_merge__seed00001"]


def test_process_evaluation_equals_in_process(process_pool, policy, local_eval):
    scs, ref = local_eval
    res = evaluate_policy(policy, scs, "topk:5", num_rollouts=2, seed=3, batch_scenes=1, progress=False,
                          pool=process_pool, worker_threads=1)
    assert _same_rows(ref.rows, res.rows) and ref.entropy == res.entropy and ref.k_by_step == res.k_by_step
    other_seed = evaluate_policy(policy, scs, "topk:5", num_rollouts=2, seed=4, batch_scenes=1, progress=False)
    assert not _same_rows(ref.rows, other_seed.rows)  # the comparison can fail


@pytest.mark.sumo
def test_simulate_batch_mode_one_row_per_run(tmp_path, capsys):
    from r1sim_sumo.cli import main

    rows = {}
    for backend in ("local", "process"):
        out = tmp_path / f"{backend}.json"
        assert main(["simulate", "--network", "lane_drop", "motorway_merge", "--seeds", "0", "1", "--native", "--end", "3",
                     "--backend", backend, "--workers", "2", "--no-progress", "--json", str(out)]) == 0
        runs = json.loads(out.read_text())["runs"]
        rows[backend] = [(r["sumocfg"].split("/")[-1], r["seed"], r["departed"], r["vkm_all"]) for r in runs]
    assert rows["local"] == rows["process"]
    assert [(c, s) for c, s, _, _ in rows["local"]] == [("lane_drop.sumocfg", 0), ("lane_drop.sumocfg", 1),
                                                        ("motorway_merge.sumocfg", 0), ("motorway_merge.sumocfg", 1)]
    printed = capsys.readouterr().out
    assert printed.count(" native ") == 8 and "0 retried" in printed


# ---------------------------------------------------------------------------- Ray


@pytest.mark.ray
def test_ray_pool_order_and_killed_actor_retried(ray_pool, tmp_path):
    _check_ordered_and_crash_survived(ray_pool, tmp_path)
    assert ray_pool.stats.worker_restarts >= 3


@pytest.mark.ray
def test_ray_evaluation_equals_in_process(ray_pool, policy, local_eval):
    scs, ref = local_eval
    res = evaluate_policy(policy, scs, "topk:5", num_rollouts=2, seed=3, batch_scenes=1, progress=False, pool=ray_pool)
    assert _same_rows(ref.rows, res.rows) and ref.entropy == res.entropy


@pytest.mark.ray
@pytest.mark.sumo
def test_ray_generation_equals_in_process(ray_pool, local_generation, tmp_path):
    out = run_generation_jobs(_tiny_jobs(), tmp_path / "ray", workers=2, backend="ray", progress=False)
    _same_dataset(local_generation, out)
