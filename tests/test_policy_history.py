"""Policy-then-SUMO windows (r1sim_sumo.data.policy_history): schedule, controller pause/resume, masked history labels."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from r1sim_sumo.data.policy_history import (
    DECISION_STEPS,
    FUTURE_STEPS,
    LABEL_FROM_TOKEN,
    PolicyHistorySettings,
    phase_schedule,
)
from r1sim_sumo.scenario import CURRENT_INDEX, N_WINDOW_10HZ
from r1sim_sumo.tokens.batch import TokenizedDataset, collate, mask_history_labels


def compact_and_reference(scenarios, root):
    """Write ``scenarios`` as train and val splits under ``root``, build a small vocabulary and the compact dataset;
    returns ``(CompactTokenDataset train, TokenizedDataset train)`` of the same scenes (also used by other tests)."""
    from r1sim_sumo.scenario import write_dataset
    from r1sim_sumo.tokens.compact import CompactTokenDataset, build_compact
    from r1sim_sumo.tokens.motion_vocab import VocabBuildConfig
    from r1sim_sumo.tokens.vocab_build import build_vocab_from_dataset

    for split in ("train", "val"):
        write_dataset(root / split, scenarios, shard_size=4)
    vocab, _ = build_vocab_from_dataset(scenarios, VocabBuildConfig(size=(64, 16, 16), heldout_fraction=0.0,
                                                                    min_real_segments=10, n_synthetic=300))
    build_compact(root, vocab, root / "tok", workers=1, progress=False)
    return CompactTokenDataset(root / "tok", "train"), TokenizedDataset(root / "train", vocab)


def test_schedule_alternates_policy_phases_and_one_window_of_sumo():
    s = PolicyHistorySettings("r1sim-nano", (4.0, 16.0))
    n_rec = 6000
    hand, starts = phase_schedule(n_rec, s, seed=3)
    assert len(hand) >= 20 and starts == [h - CURRENT_INDEX for h in hand]
    prev_end = 0  # the policy drives from here to the next hand-over
    for h in hand:
        phase = h - prev_end
        assert 40 <= phase <= 160 + DECISION_STEPS and phase % DECISION_STEPS == 0
        assert h - CURRENT_INDEX + N_WINDOW_10HZ - 1 < n_rec  # the window's future ends inside the recording
        prev_end = h + FUTURE_STEPS
    assert phase_schedule(n_rec, s, seed=3) == (hand, starts)
    assert phase_schedule(n_rec, s, seed=4) != (hand, starts)


def test_settings_are_checked():
    with pytest.raises(ValueError, match="policy_history_s"):
        PolicyHistorySettings("r1sim-nano", (0.5, 4.0))
    with pytest.raises(ValueError, match="policy_history_drive"):
        PolicyHistorySettings("r1sim-nano", drive="teleport")


def test_masking_drops_only_the_history_labels():
    from r1sim_sumo.tokens.matching import TokenizedAgents

    tok = np.arange(2 * 18).reshape(2, 18)
    a = TokenizedAgents.__new__(TokenizedAgents)
    a.token, a.target = tok.copy(), None
    mask_history_labels(a, 0)
    assert a.target is None  # nothing to mask: labels stay the tokens
    mask_history_labels(a, LABEL_FROM_TOKEN)
    assert (a.target[:, :LABEL_FROM_TOKEN] == -1).all() and (a.target[:, LABEL_FROM_TOKEN:] == tok[:, LABEL_FROM_TOKEN:]).all()
    assert (a.token == tok).all()  # inputs unchanged


@pytest.mark.highway
def test_compact_and_scenario_paths_mask_the_same_labels(tmp_path):
    from r1sim_sumo.data.highway_reference import generate_highway_scenarios
    from r1sim_sumo.train.pretrain import collate_targets

    scs = generate_highway_scenarios("merge-v0", seed=0, n_episodes=1, episode_s=12.0, stride_steps=10, progress=False)
    assert len(scs) >= 4
    for sc in scs[::2]:  # every other window: a policy-driven history
        sc.metadata["label_from_token"] = LABEL_FROM_TOKEN
    comp, ref = compact_and_reference(scs, tmp_path)
    for i in range(len(scs)):
        masked = i % 2 == 0
        assert comp.label_from(i) == (LABEL_FROM_TOKEN if masked else 0)
        a, b = comp[i].agents, ref[i].agents
        assert np.array_equal(a.token, b.token)
        if masked:
            assert np.array_equal(a.target, b.target)
            assert (a.target[:, :LABEL_FROM_TOKEN] == -1).all()
            assert np.array_equal(a.target[:, LABEL_FROM_TOKEN:], a.token[:, LABEL_FROM_TOKEN:])
        else:
            assert a.target is None and b.target is None
        x = comp.noised(i, 3, np.random.default_rng([1, i]))
        y = ref.noised(i, 3, np.random.default_rng([1, i]))
        assert np.array_equal(x.agents.target, y.agents.target)
        if masked:
            assert (x.agents.target[:, :LABEL_FROM_TOKEN] == -1).all()
    # a batch mixing both: the unmasked scene is labelled by its own tokens
    scenes = [comp[0], comp[1]]
    batch = collate(scenes)
    t = collate_targets(scenes, batch)
    n0, n1 = scenes[0].agents.num_agents, scenes[1].agents.num_agents
    assert (t[0, :n0, :LABEL_FROM_TOKEN] == -1).all()
    assert torch.equal(t[1, :n1], torch.from_numpy(scenes[1].agents.token.astype(np.int64)))


@pytest.mark.sumo
def test_controller_pause_gives_every_vehicle_to_sumo_until_resume():
    from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary
    from r1sim_sumo.model.untrained import untrained_policy
    from r1sim_sumo.resources import network_files
    from r1sim_sumo.sim.sumo_controller import SumoController

    ensure_sumo_home()
    import libsumo

    torch.set_num_threads(1)
    libsumo.start([sumo_binary("sumo"), "-c", str(network_files("motorway_merge")["sumocfg"]), "--step-length", "0.1",
                   "--no-step-log", "true", "--no-warnings", "true", "--seed", "0", "--end", "200"])
    try:
        ctrl = SumoController(libsumo, untrained_policy(0), drive="commands", offroad_margin_m=1e6, map_cache_dir=None)
        for _ in range(60):
            libsumo.simulationStep()
            ctrl.step()
        taken = ctrl.controlled_ids()
        assert taken
        ctrl.pause()
        for _ in range(30):  # new vehicles enter meanwhile: none is taken
            libsumo.simulationStep()
            ctrl.step()
            assert ctrl.controlled_ids() == []
        for v in taken:
            if v in libsumo.vehicle.getIDList():
                assert libsumo.vehicle.getSpeedMode(v) == 31  # SUMO's own checks are back
        assert ctrl.stats.handbacks["paused"] == len(taken)
        ctrl.resume()
        for _ in range(DECISION_STEPS):
            libsumo.simulationStep()
            ctrl.step()
        back = set(ctrl.controlled_ids())
        assert back & set(taken)  # the paused vehicles are driven by the policy again
        assert len(back) >= len(set(taken) & set(libsumo.vehicle.getIDList()))
    finally:
        ctrl.close()


@pytest.mark.sumo
def test_generated_windows_start_at_the_hand_overs_and_mask_the_history():
    from r1sim_sumo.data.sumo_reference import RunStats, SumoGenConfig, generate_sumo_scenarios

    cfg = SumoGenConfig(network="motorway_merge", seed=1, duration_s=40.0, warmup_s=20.0, policy_history="r1sim-nano",
                        policy_history_s=(2.0, 6.0))
    hand, starts = phase_schedule(400, cfg.policy_history_settings(), cfg.seed)
    stats = RunStats()
    scs = generate_sumo_scenarios(cfg, stats=stats)
    assert len(scs) == len(starts) == cfg.num_windows() >= 2
    for sc, s in zip(scs, starts, strict=True):
        assert sc.metadata["label_from_token"] == LABEL_FROM_TOKEN
        assert sc.metadata["start_time_s"] == pytest.approx(20.0 + s * 0.1)
    assert stats.extra["policy_history_controlled_total"] > 0 and stats.extra["policy_history_vkm_controlled"] > 0
