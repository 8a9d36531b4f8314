"""Which checkpoints a learning curve plots and where (r1sim_sumo.train.learning_curve._run_points)."""

import json
from pathlib import Path

import pytest

from r1sim_sumo.train.learning_curve import _run_points


def _ckpt(d: Path, train: dict | None = None) -> None:
    d.mkdir(parents=True)
    (d / "checkpoint.json").write_text(json.dumps({"training": {"train": train or {}}}))


def _finetune_run(run: Path, snapshot: str, init, threads: int, log: str) -> Path:
    """A fine-tuning run folder: one exported snapshot without counts, its config and ``log.csv`` (``log``)."""
    _ckpt(run / snapshot)
    (run / "config.yaml").write_text(f"init_checkpoint: {init}\nthreads: {threads}\n")
    (run / "log.csv").write_text(log)
    return run


def test_pretraining_run_points_carry_tokens_hours_and_val_nll(tmp_path):
    run = tmp_path / "pre"
    _ckpt(run / "ckpt-000100", {"agent_tokens_seen": 1000, "cpu_hours": 0.5})
    _ckpt(run / "ckpt-000200", {"agent_tokens_seen": 2000, "cpu_hours": 1.0})
    (run / "config.yaml").write_text("init_checkpoint: null\n")
    (run / "log.csv").write_text("step,loss,val_nll\n100,2.0,1.5\n150,1.9,\n200,1.8,\n")
    pts = _run_points(run)
    assert [p["name"] for p in pts] == ["pre@100", "pre@200"]
    assert pts[0]["val_nll"] == 1.5 and pts[1]["val_nll"] is None  # no eval logged at step 200
    assert pts[1]["agent_tokens"] == 2000 and pts[1]["cpu_hours"] == 1.0


def test_pretraining_run_from_a_snapshot_is_placed_after_its_compute(tmp_path):
    start = tmp_path / "pre" / "ckpt-003000"
    _ckpt(start, {"agent_tokens_seen": 14000, "cpu_hours": 2.0})
    run = tmp_path / "more"
    _ckpt(run / "ckpt-000800", {"agent_tokens_seen": 3000, "cpu_hours": 0.5})
    (run / "config.yaml").write_text(f"init_checkpoint: {start}\n")
    (run / "log.csv").write_text("step,loss,val_nll\n800,2.0,1.2\n")
    pts = _run_points(run)
    assert [p["name"] for p in pts] == ["more@0", "more@800"]
    assert pts[0]["agent_tokens"] == 14000 and pts[0]["cpu_hours"] == 2.0
    assert pts[1]["agent_tokens"] == 17000 and abs(pts[1]["cpu_hours"] - 2.5) < 1e-9
    (run / "config.yaml").write_text("init_checkpoint: r1sim-nano\n")  # a bundled name: the campaigns start at 0
    pts = _run_points(run)
    assert pts[0]["cpu_hours"] == 0.0 and pts[1]["agent_tokens"] == 3000


def test_finetune_from_a_continued_run_counts_the_whole_chain(tmp_path):
    a = tmp_path / "a" / "ckpt-003000"
    _ckpt(a, {"agent_tokens_seen": 14000, "cpu_hours": 2.0})
    (tmp_path / "a" / "config.yaml").write_text("init_checkpoint: r1sim-nano\n")
    b = tmp_path / "b" / "ckpt-000800"
    _ckpt(b, {"agent_tokens_seen": 3000, "cpu_hours": 0.5})
    (tmp_path / "b" / "config.yaml").write_text(f"init_checkpoint: {a}\n")
    run = tmp_path / "sft"
    _ckpt(run / "ckpt-000050")
    (run / "config.yaml").write_text(f"init_checkpoint: {b}\nthreads: 1\n")
    (run / "log.csv").write_text("iter,rollout_s,update_s\n50,36,0\n")  # one row for 50 iterations of 36 s
    pts = _run_points(run)
    assert pts[0]["agent_tokens"] == 17000 and abs(pts[0]["cpu_hours"] - 2.5) < 1e-9
    assert abs(pts[1]["cpu_hours"] - 3.0) < 1e-9


def test_finetune_run_points_start_at_their_checkpoint_and_add_compute_across_resumes(tmp_path):
    start = tmp_path / "pre" / "ckpt-000200"
    _ckpt(start, {"agent_tokens_seen": 2000, "cpu_hours": 1.0})
    # wall_s restarts after a resume; rollout_s + update_s do not depend on it
    run = _finetune_run(tmp_path / "sft", "ckpt-000002", start, 2,
                        "iter,rollout_s,update_s,wall_s\n1,600,300,900\n2,900,0,900\n3,1,1,2\n")
    pts = _run_points(run)
    assert [p["name"] for p in pts] == ["sft@0", "sft@2"]
    assert pts[0]["path"] == str(start) and pts[0]["agent_tokens"] == 2000 and pts[0]["cpu_hours"] == 1.0
    assert pts[1]["agent_tokens"] == 2000
    assert abs(pts[1]["cpu_hours"] - (1.0 + 1800 * 2 / 3600)) < 1e-9


def test_free_road_probe_drives_along_its_lane():
    """The probe's lone vehicle starts on the lane at v0 and follows its plans along it (a wrong frame or a lost
    history would throw it off the lane or stop it)."""
    import numpy as np

    from r1sim_sumo import load_policy
    from r1sim_sumo.evaluate_free_road import START_M, drive_alone, lane_axis

    axis = lane_axis()
    _, p0, u, yaw0, _ = axis
    xy, yaw = drive_alone(load_policy(), 25.0, seed=0, decisions=4, axis=axis)
    assert xy.shape == (11 + 20, 2) and yaw.shape == (31,)
    rel = xy - p0
    along, across = rel @ u, rel @ np.array([-u[1], u[0]])
    assert abs(along[0] - START_M) < 1e-6 and np.all(np.diff(along) > 0)  # always forward
    assert np.abs(across).max() < 1.5  # stays in its 3.2 m lane
    v_end = (along[-1] - along[-6]) / 0.5
    assert 15.0 < v_end < 40.0, v_end


def test_free_road_probe_takes_the_sampler():
    """``sampler='greedy'`` (the drop-in's) drives the same path whatever the seed; top-5 draws differ between seeds."""
    import numpy as np

    from r1sim_sumo import load_policy
    from r1sim_sumo.evaluate_free_road import drive_alone, lane_axis

    axis, pol = lane_axis(), load_policy()
    g0, _ = drive_alone(pol, 20.0, seed=0, decisions=6, axis=axis, sampler="greedy")
    g1, _ = drive_alone(pol, 20.0, seed=1, decisions=6, axis=axis, sampler="greedy")
    assert np.array_equal(g0, g1)
    t = [drive_alone(pol, 20.0, seed=s, decisions=6, axis=axis, sampler="topk:5")[0] for s in range(3)]
    assert not all(np.array_equal(t[0], x) for x in t[1:])


def test_desired_speed_tracking_reports_each_run_and_the_error_to_its_desired_speed():
    """One row per (desired, v0) with an end speed per seed; the error is the mean |end - desired| of those runs."""
    import numpy as np

    from r1sim_sumo import load_policy
    from r1sim_sumo.evaluate_free_road import desired_speed_tracking

    t = desired_speed_tracking(load_policy(), desired=(20.0, 35.0), v0s=(22.0,), seeds=2, decisions=3)
    assert [(r["desired_mps"], r["v0_mps"]) for r in t["rows"]] == [(20.0, 22.0), (35.0, 22.0)]
    ends = np.array([r["end_mps"] for r in t["rows"]])  # [2 desired, 2 seeds]
    assert ends.shape == (2, 2) and np.all((ends > 10.0) & (ends < 40.0))  # 1.5 s from a steady 22 m/s
    assert t["mae_mps"] == pytest.approx(np.mean(np.abs(ends - np.array([[20.0], [35.0]]))))


def test_acceleration_map_rows_and_means():
    """One row per (v0, gap) with a finite acceleration; the two means are over the rows with and without a gap."""
    import numpy as np

    from r1sim_sumo import load_policy
    from r1sim_sumo.evaluate_free_road import acceleration_map

    m = acceleration_map(load_policy(), v0s=(15.0, 25.0), gaps=(0.0, 8.0), seeds=2)
    assert [(r["v0_mps"], r["gap_mps"]) for r in m["rows"]] == [(15.0, 0.0), (15.0, 8.0), (25.0, 0.0), (25.0, 8.0)]
    acc = np.array([r["accel_mps2"] for r in m["rows"]])
    assert np.all(np.isfinite(acc)) and np.all(np.abs(acc) < 8.0)  # within what a car can do in 1 s
    assert m["mean_accel_gap_mps2"] == pytest.approx(acc[[1, 3]].mean())
    assert m["mean_accel_no_gap_mps2"] == pytest.approx(acc[[0, 2]].mean())


def test_platoon_probe_keeps_its_order_and_lane():
    """The platoon starts at its headways in one lane, front first, and every vehicle drives forward along the lane
    without passing the one ahead (a mixed-up agent order or frame would show as overlaps or lane departures)."""
    import numpy as np

    from r1sim_sumo import load_policy
    from r1sim_sumo.evaluate_free_road import drive_platoon, lane_axis

    axis = lane_axis()
    _, p0, u, _, _ = axis
    xy = drive_platoon(load_policy(), 10.0, n=3, headway_s=1.5, seed=0, decisions=4, axis=axis)
    assert xy.shape == (3, 11 + 20, 2)
    rel = xy - p0
    along, across = rel @ u, rel @ np.array([-u[1], u[0]])
    assert np.allclose(along[:-1, 0] - along[1:, 0], 5.0 + 1.5 * 10.0)  # centre spacing at the start
    assert np.all(np.diff(along, axis=1) > 0)  # all forward
    assert np.all(along[:-1] - along[1:] > 5.0)  # no one reaches the one ahead
    assert np.abs(across).max() < 1.5


def test_a_run_from_a_re_shipped_bundled_name_starts_at_the_snapshot_with_its_recorded_weights(tmp_path):
    """A run started from r1sim-nano records the weights' SHA-256 (init.json); once another policy is shipped under
    that name, the run's starting point is the sibling snapshot holding those weights, not today's r1sim-nano."""
    from r1sim_sumo.train.pretrain import record_init

    old = tmp_path / "prev" / "ckpt-000800"
    _ckpt(old, {"agent_tokens_seen": 5000, "cpu_hours": 1.0})
    meta = json.loads((old / "checkpoint.json").read_text())
    meta["weights"] = {"sha256": "ab" * 32}
    (old / "checkpoint.json").write_text(json.dumps(meta))
    run = tmp_path / "next"
    _ckpt(run / "ckpt-000400", {"agent_tokens_seen": 100, "cpu_hours": 0.1})
    (run / "config.yaml").write_text("init_checkpoint: r1sim-nano\n")
    (run / "log.csv").write_text("step,loss,val_nll\n400,2.0,1.2\n")
    record_init(run, "r1sim-nano", "ab" * 32)  # not the bundled nano's weights
    pts = _run_points(run)
    assert pts[0]["name"] == "next@0" and pts[0]["path"] == str(old)
    assert pts[0]["agent_tokens"] == 5000 and pts[1]["agent_tokens"] == 5100
    record_init(run, "r1sim-nano", None)  # nothing recorded: the name as it is
    assert _run_points(run)[0]["path"] == "r1sim-nano"


def test_a_run_whose_recorded_start_weights_are_gone_has_no_start_point(tmp_path, capsys):
    """Weights restored into a plain folder beside the run are found; when no folder holds the recorded weights the
    start point is left out with a message (loading today's r1sim-nano would put other weights at step 0)."""
    from r1sim_sumo.train.pretrain import record_init

    run = tmp_path / "next"
    _ckpt(run / "ckpt-000400", {"agent_tokens_seen": 100, "cpu_hours": 0.1})
    (run / "config.yaml").write_text("init_checkpoint: r1sim-nano\n")
    (run / "log.csv").write_text("step,loss,val_nll\n400,2.0,1.2\n")
    record_init(run, "r1sim-nano", "cd" * 32)
    pts = _run_points(run)
    assert [p["name"] for p in pts] == ["next@400"] and pts[0]["agent_tokens"] == 100
    assert "cdcdcdcd" in capsys.readouterr().out
    restored = tmp_path / "nano_old"
    _ckpt(restored, {"agent_tokens_seen": 7000, "cpu_hours": 2.0})
    meta = json.loads((restored / "checkpoint.json").read_text())
    meta["weights"] = {"sha256": "cd" * 32}
    (restored / "checkpoint.json").write_text(json.dumps(meta))
    pts = _run_points(run)
    assert pts[0]["name"] == "next@0" and pts[0]["path"] == str(restored) and pts[1]["agent_tokens"] == 7100


def test_cache_keys_keep_pre_decoding_entries_and_separate_decodings():
    from r1sim_sumo.train.learning_curve import cache_key

    assert cache_key("runs/a/ckpt-000100", "tokens") == "runs/a/ckpt-000100"  # the entries written before session 12
    assert cache_key("runs/a/ckpt-000100", "central") != cache_key("runs/a/ckpt-000100", "tokens")


def test_an_earlier_shipped_policy_is_restored_from_git_by_its_weights_hash(tmp_path):
    """The bundled nano's weights as committed are found in git by their SHA-256 and written out checked; a hash no
    version has gives None."""
    import subprocess

    from r1sim_sumo.model.checkpoint import BUNDLED_DIR
    from r1sim_sumo.train.learning_curve import restore_shipped_from_git

    if subprocess.run(["git", "-C", str(BUNDLED_DIR), "log", "-1", "--format=%H", "--", "r1sim-nano"],
                      capture_output=True, text=True).stdout.strip() == "":
        pytest.skip("no git history of the bundled checkpoints here (an installed copy)")
    sha = json.loads((BUNDLED_DIR / "r1sim-nano" / "checkpoint.json").read_text())["weights"]["sha256"]
    out = restore_shipped_from_git("r1sim-nano", sha, tmp_path)
    assert out == tmp_path / f"r1sim-nano-{sha[:8]}"
    assert (out / "model.safetensors").read_bytes() == (BUNDLED_DIR / "r1sim-nano" / "model.safetensors").read_bytes()
    assert restore_shipped_from_git("r1sim-nano", "ef" * 32, tmp_path / "none") is None


def test_an_evaluated_checkpoint_with_the_same_weights_is_found_by_its_hash(tmp_path):
    """A copy of evaluated weights (same recorded SHA-256) reuses that entry, only under the same decoding."""
    from r1sim_sumo.train.learning_curve import cache_key, evaluated_twin

    for name, sha in (("a", "11" * 32), ("copy_of_a", "11" * 32), ("b", "22" * 32)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "checkpoint.json").write_text(json.dumps({"weights": {"sha256": sha}}))
    a = str(tmp_path / "a")
    evaluated = {cache_key(a, "central"): {"weights_sha256": "11" * 32, "rmm": 0.8}}
    assert evaluated_twin(evaluated, str(tmp_path / "copy_of_a"), "central") == cache_key(a, "central")
    assert evaluated_twin(evaluated, str(tmp_path / "copy_of_a"), "tokens") is None
    assert evaluated_twin(evaluated, str(tmp_path / "b"), "central") is None
    assert evaluated_twin(evaluated, str(tmp_path / "no_such"), "central") is None


def test_finetune_of_a_finetuned_checkpoint_is_placed_after_both_runs_compute(tmp_path):
    """A fine-tuning run started from another one's exported weights (no counts of their own): the first run's start
    plus its compute, then the second's; a run logging every 5th iteration counts each row for 5 iterations."""
    start = tmp_path / "pre" / "ckpt-000200"
    _ckpt(start, {"agent_tokens_seen": 2000, "cpu_hours": 1.0})
    grpo = _finetune_run(tmp_path / "grpo", "final", start, 1, "iter,rollout_s,update_s\n1,1800,0\n2,1800,0\n")
    sft = _finetune_run(tmp_path / "sft", "ckpt-000010", grpo / "final", 1, "iter,rollout_s,update_s\n5,360,0\n10,360,0\n")
    pts = _run_points(sft)
    assert pts[0]["agent_tokens"] == 2000 and abs(pts[0]["cpu_hours"] - 2.0) < 1e-9  # 1.0 + the GRPO run's hour
    assert abs(pts[1]["cpu_hours"] - (2.0 + 10 * 360 / 3600)) < 1e-9


def test_checkpoints_without_cpu_hours_are_plotted_in_the_order_given():
    """Checkpoints passed one by one (fine-tunes record no CPU hours) used to leave every panel empty."""
    from r1sim_sumo.train.learning_curve import _short_name, plot_series

    pts = [{"name": f"runs/g/ckpt-0000{i}0", "run": "checkpoint", "cpu_hours": None, "rmm": 0.80 + i / 100} for i in (1, 2, 3)]
    pts.append({"name": "runs/other/final", "run": "checkpoint", "cpu_hours": None, "rmm": None})  # no value: left out
    [(run, xs, ys)] = plot_series(pts, "rmm")
    assert run == "checkpoint" and xs == [0.0, 1.0, 2.0] and ys == pytest.approx([0.81, 0.82, 0.83])
    assert _short_name("runs/g/ckpt-000030") == "g@30" and _short_name("runs/other/final") == "other/final"
    # with CPU hours known everywhere the x axis is compute, each run sorted by it
    hours = [{"name": "a", "run": "r", "cpu_hours": 2.0, "rmm": 0.9}, {"name": "b", "run": "r", "cpu_hours": 1.0, "rmm": 0.8},
             {"name": "c", "run": "s", "cpu_hours": 0.5, "rmm": 0.7}]
    assert plot_series(hours, "rmm") == [("r", [1.0, 2.0], [0.8, 0.9]), ("s", [0.5], [0.7])]
