"""Fault injection: real subprocesses SIGKILLed at random moments then resumed (identical weights and log, the state
folder never corrupt), NaN logits in the samplers, SUMO killed during `r1sim simulate --traci`."""

from __future__ import annotations

import pytest

from r1sim_sumo.reliability import faults


def test_nan_logits_fall_back_and_warn():
    res = faults.nan_logits_guard()
    assert res["passed"], res
    assert set(res["samplers"]) >= {"greedy", "topk:5", "entropy:16,80", "full"}


@pytest.mark.sumo
def test_sumo_killed_during_traci_simulate_gives_partial_summary(tmp_path):
    res = faults.sumo_crash_during_simulate(tmp_path, kill_after_s=2.0)
    assert res["returncode"] == 3 and not res["traceback"], res
    assert "SUMO stopped responding" in res["error_line"]
    assert res["partial_sim_s"] and res["partial_sim_s"] > 0 and res["balanced"] is True


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_pretrain_sigkill_and_resume_is_exact(tmp_path, seed):
    res = faults.kill_and_resume("pretrain", tmp_path, steps=16, kills=2, seed=seed)
    assert res["identical_weights"] and res["identical_log"] and res["state_never_corrupt"], res
    assert any(k["killed"] for k in res["kills"])


@pytest.mark.slow
def test_finetune_sigkill_and_resume_is_exact(tmp_path):
    res = faults.kill_and_resume("finetune", tmp_path, steps=8, kills=2, seed=0)
    assert res["identical_weights"] and res["identical_log"] and res["state_never_corrupt"], res
    assert any(k["killed"] for k in res["kills"])
