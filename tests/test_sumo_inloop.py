"""SUMO-in-the-loop GRPO rollouts (r1sim_sumo.train.sumo_inloop): record format, forced collisions, end to end."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.sumo


@pytest.fixture(scope="module")
def states_data(tmp_path_factory):
    """A 10 s motorway_merge run with a SUMO state at each window's current index (2 windows)."""
    from r1sim_sumo.data.sumo_reference import SumoGenConfig, generate_sumo_scenarios
    from r1sim_sumo.scenario import ScenarioDataset, write_dataset

    root = tmp_path_factory.mktemp("states")
    cfg = SumoGenConfig(network="motorway_merge", seed=0, duration_s=12.0, warmup_s=50.0, stride_steps=25, save_states=True,
                        demand_scale=0.7)
    write_dataset(root, generate_sumo_scenarios(cfg, state_root=root))
    return ScenarioDataset(root)


@pytest.fixture(scope="module")
def checkpoint(policy, tmp_path_factory):
    from r1sim_sumo.model.checkpoint import save_checkpoint

    return save_checkpoint(tmp_path_factory.mktemp("ck") / "policy", policy.model, policy.vocab)


def _scenes(ds, vocab, idx):
    from r1sim_sumo.tokens.batch import collate, tokenize_scenario

    scenes = [tokenize_scenario(ds[i], vocab) for i in idx]
    return scenes, collate(scenes)


def test_record_matches_rollout_result(policy, states_data, checkpoint):
    from r1sim_sumo.rollout.engine import rollout
    from r1sim_sumo.rollout.samplers import parse_sampler
    from r1sim_sumo.train.grpo import GRPOConfig, GRPOLearner
    from r1sim_sumo.train.sumo_inloop import PolicyRef, SumoRolloutSource

    idx = [0, 1]
    scenes, batch = _scenes(states_data, policy.vocab, idx)
    G, F = 2, 4
    with SumoRolloutSource(states_data, workers=0) as src:
        res, extra = src.rollout(PolicyRef(str(checkpoint)), idx, scenes, G, "topk:32", torch.Generator().manual_seed(0), F)
    ref = rollout(policy.model, policy.vocab, batch, G, parse_sampler("topk:32"), generator=torch.Generator().manual_seed(0),
                  num_steps=F)
    for f in ("token", "logp", "logp_full", "entropy", "k", "pose_xy", "pose_yaw", "xy_10hz", "yaw_10hz", "valid", "sim_mask"):
        a, b = getattr(res, f), getattr(ref, f)
        assert a.shape == b.shape and a.dtype == b.dtype, f
    assert extra.shape == res.token.shape and extra.dtype == torch.bool
    assert torch.equal(res.sim_mask, ref.sim_mask)
    act = res.sim_mask[None, :, :, None] & (res.token >= 0)
    assert act.sum() > 0.8 * res.sim_mask.sum() * G * F  # nearly every agent keeps driving
    # boundary poses are the token chain: pose 0 = "now" of the reference, 10 Hz states hit the boundaries
    assert torch.allclose(res.pose_xy[:, :, :, 0], batch.pose_xy[None, :, :, 2].expand_as(res.pose_xy[:, :, :, 0]))
    assert torch.allclose(res.xy_10hz[..., ::5, :][res.valid], res.pose_xy[res.valid], atol=1e-3)
    # the learner's teacher-forced forward reproduces the workers' log-probs (ratio 1 before the first update)
    cfg = GRPOConfig(num_rollouts=G, batch_scenes=2, num_steps=F, sampler="topk:32", ppo_epochs=1, num_minibatches=1,
                     freeze="head")
    learner = GRPOLearner(copy.deepcopy(policy.model), copy.deepcopy(policy.model), policy.vocab, cfg)
    st = learner.grpo_iteration(batch, torch.Generator().manual_seed(1), result=res, extra_collision=extra)
    assert st["first_ratio_dev"] < 1e-3
    assert np.isfinite(st["loss"])


class _Ram:
    """A policy stand-in: agent ``follower`` always takes the fastest straight token, everyone else stands still."""

    def __init__(self, model, follower: int, fast_token: int):
        self.model, self.follower, self.fast = model, follower, fast_token

    def init_rollout(self, *a, **kw):
        return self.model.init_rollout(*a, **kw)

    def step(self, cache, k, prev, xy, yaw, valid):
        logits = self.model.step(cache, k, prev, xy, yaw, valid)
        out = torch.full_like(logits, float("-inf"))
        out[..., 0] = 0.0
        out[:, self.follower] = float("-inf")
        out[:, self.follower, self.fast] = 0.0
        return out


def _leader_follower(batch) -> tuple[int, int]:
    """(leader, follower) agents of scene 0: same heading, < 1 m lateral offset, follower 6-40 m behind."""
    xy, yaw, ok = batch.pose_xy[0, :, 2].double(), batch.pose_yaw[0, :, 2].double(), batch.pose_valid[0, :, 2]
    best = None
    for f in torch.nonzero(ok).flatten().tolist():
        h = torch.stack([torch.cos(yaw[f]), torch.sin(yaw[f])])
        d = xy - xy[f]
        lon, lat = d @ h, d @ torch.stack([-h[1], h[0]])
        same = ok & ((yaw - yaw[f] + np.pi) % (2 * np.pi) - np.pi).abs().lt(0.1) & lat.abs().lt(1.0) & lon.gt(6) & lon.lt(40)
        for a in torch.nonzero(same).flatten().tolist():
            if best is None or lon[a] < best[0]:
                best = (float(lon[a]), a, f)
    assert best is not None, "no leader/follower pair in the scene"
    return best[1], best[2]


def test_forced_collision_is_reported_by_sumo_and_penalised(policy, states_data):
    from r1sim_sumo.data.sumo_reference import scenario_sumo_files
    from r1sim_sumo.train.rewards import RewardConfig, compute_rewards
    from r1sim_sumo.train.sumo_inloop import assemble, rollout_scene_in_sumo

    scenes, batch = _scenes(states_data, policy.vocab, [0])
    leader, follower = _leader_follower(batch)
    fast = int(np.argmax(policy.vocab.traj[0][:, -1, 0] - 10 * np.abs(policy.vocab.traj[0][:, -1, 1])))
    net, state = scenario_sumo_files(states_data[0], states_data.root)
    rec = rollout_scene_in_sumo(_Ram(policy.model, follower, fast), policy.vocab, scenes[0], net, state, seeds=[0],
                                sampler="topk:32", num_steps=8)
    assert rec.sumo_collisions > 0
    res, extra = assemble([[rec]], batch.agent_mask.shape[1])
    hit = extra[0, 0, follower]  # [F]
    assert hit.any() and extra[0, 0, leader].any()
    t = int(torch.nonzero(hit).flatten()[0])
    rw = compute_rewards(res, batch, RewardConfig(kind="spr"), extra)
    assert rw.collision[0, 0, follower, t] and rw.reward[0, 0, follower, t] < 0
    # the SUMO flag alone (no SAT among agents: reward computed on a copy without the leader) still penalises
    res_no_leader = copy.copy(res)
    res_no_leader.valid = res.valid.clone()
    res_no_leader.valid[:, :, leader] = False
    rw2 = compute_rewards(res_no_leader, batch, RewardConfig(kind="spr"), extra)
    rw_sat = compute_rewards(res_no_leader, batch, RewardConfig(kind="spr"), None)
    assert rw2.reward[0, 0, follower, t] < 0 < rw_sat.reward[0, 0, follower, t]


def test_sat_obstacles_are_all_but_the_policy_driven():
    from r1sim_sumo.train.sumo_inloop import sat_obstacle_ids

    ids = ["a", "b", "c"]
    # b is a scenario agent entering later (not controlled): SUMO drives it, so it is an obstacle; x is not a scenario agent
    assert sat_obstacle_ids(["a", "b", "c", "x"], ids, [True, False, True]) == ["b", "x"]
    assert sat_obstacle_ids(["x"], ids, [True, True, True]) == ["x"]


def test_sumo_driven_scenario_agent_is_checked_for_overlaps(policy, states_data):
    """Issue 16 item 9: a scenario agent the policy does not drive (here the leader, marked invalid at the current
    step as an agent entering later would be) is SUMO-driven; the follower ramming it is found by the SAT check."""
    from r1sim_sumo.train.sumo_inloop import rollout_scene_in_sumo, scenario_sumo_files

    scenes, batch = _scenes(states_data, policy.vocab, [0])
    leader, follower = _leader_follower(batch)
    fast = int(np.argmax(policy.vocab.traj[0][:, -1, 0] - 10 * np.abs(policy.vocab.traj[0][:, -1, 1])))
    scene = copy.deepcopy(scenes[0])
    scene.agents.pose_valid[leader, 2] = False
    net, state = scenario_sumo_files(states_data[0], states_data.root)
    rec = rollout_scene_in_sumo(_Ram(policy.model, follower, fast), policy.vocab, scene, net, state, seeds=[0],
                                sampler="topk:32", num_steps=8)
    assert not rec.sim_mask[leader] and rec.sim_mask[follower]
    assert rec.sat_collisions > 0 and rec.collision[0, follower].any()
    no_sat = rollout_scene_in_sumo(_Ram(policy.model, follower, fast), policy.vocab, scene, net, state, seeds=[0],
                                   sampler="topk:32", num_steps=8, check_sat=False)
    assert no_sat.sat_collisions == 0


def test_finetune_with_sumo_source_two_workers_equals_in_process(policy, states_data, tmp_path):
    """Issue 8: a short SUMO-in-the-loop GRPO run gives the same log and weights with 2 worker processes as in-process."""
    import csv

    from safetensors.torch import load_file

    from r1sim_sumo.train.grpo import GRPOConfig, finetune

    rows, weights = {}, {}
    for workers in (0, 2):
        cfg = GRPOConfig(train_data=str(states_data.root), rollout_source="sumo", sumo_workers=workers, num_rollouts=2,
                         batch_scenes=1, num_steps=3, sampler="topk:32", ppo_epochs=1, num_minibatches=1, max_iters=1,
                         threads=1, freeze="head", out_dir=str(tmp_path / f"run{workers}"))
        final = finetune(cfg, progress=False, policy=policy)
        weights[workers] = load_file(str(final / "model.safetensors"))
        rows[workers] = list(csv.DictReader(open(tmp_path / f"run{workers}" / "log.csv")))
    assert len(rows[2]) == 1 and np.isfinite(float(rows[2][0]["reward"])) and float(rows[2][0]["first_ratio_dev"]) < 1e-3
    for key in ("reward", "collision_rate", "agent_collision_rate", "loss", "kl"):
        assert rows[0][0][key] == rows[2][0][key], key
    assert weights[0].keys() == weights[2].keys()
    assert all(torch.equal(weights[0][k], weights[2][k]) for k in weights[0])
    init = {f"model.{k}": v for k, v in policy.model.state_dict().items()}  # checkpoint keys carry "model."
    assert any(not torch.equal(v, init[k]) for k, v in weights[2].items() if k in init)  # the iteration did update


def test_sumo_source_refuses_a_dataset_without_states(policy, tmp_path):
    from r1sim_sumo.data.sumo_reference import SumoStateError, scenario_sumo_files
    from r1sim_sumo.scenario import Scenario
    from r1sim_sumo.train.grpo import GRPOConfig

    with pytest.raises(ValueError, match="rollout_source"):
        GRPOConfig(rollout_source="carla")
    with pytest.raises(ValueError, match="sft"):
        GRPOConfig(rollout_source="sumo", method="sft")
    with pytest.raises(ValueError, match="sumo_backend 'dask'"):
        GRPOConfig(rollout_source="sumo", sumo_backend="dask")
    assert GRPOConfig(rollout_source="sumo", sumo_backend="ray").sumo_backend == "ray"
    sc = Scenario.__new__(Scenario)
    sc.metadata = {"network": "motorway_merge"}
    with pytest.raises(SumoStateError, match="save-states"):
        scenario_sumo_files(sc, tmp_path)


# The single-process reference runs in this pytest process (workers=0), after whatever SUMO work earlier tests did:
# every rollout reloads SUMO from its state file (sumo_launch.sumo_start(state_file=...)), so nothing a process ran before leaks
# into a rollout. Sharding over 2 workers / actors must not change anything, SUMO's collision reports included.
@pytest.mark.parametrize("backend", ["process", pytest.param("ray", marks=[pytest.mark.ray, pytest.mark.slow])])
def test_sumo_inloop_rollouts_equal_in_one_process_and_in_workers(policy, states_data, checkpoint, backend):
    """Scale-out (issue 8): the same SUMO-in-the-loop GRPO rollouts from one process or 2 worker processes / actors."""
    if backend == "ray":
        pytest.importorskip("ray")
    from r1sim_sumo.train.sumo_inloop import PolicyRef, SumoRolloutSource

    idx = [0, 1]
    scenes, _ = _scenes(states_data, policy.vocab, idx)
    out = {}
    for name, workers, be in (("inline", 0, "process"), (backend, 2, backend)):
        with SumoRolloutSource(states_data, workers=workers, backend=be) as src:
            out[name] = src.rollout(PolicyRef(str(checkpoint)), idx, scenes, 4, "topk:32", torch.Generator().manual_seed(3), 4)
    (a, ea), (b, eb) = out["inline"], out[backend]
    assert torch.equal(a.token, b.token) and torch.allclose(a.xy_10hz, b.xy_10hz) and torch.allclose(a.logp, b.logp)
    assert torch.equal(ea, eb), f"{int((ea != eb).sum())} of {ea.numel()} SUMO collision flags differ"
    assert (a.token >= 0).any()


def test_sumo_restarts_from_a_state_do_not_depend_on_what_ran_before(states_data):
    """SUMO's loadState discards the saved number of RNG draws from the generator *as it is*: a second loadState in
    a running simulation gives other dawdling and insertions. sumo_start(state_file=...) reloads, so it does not."""
    from r1sim_sumo.data.sumo_reference import scenario_sumo_files
    from r1sim_sumo.sumo_launch import sumo_close, sumo_start

    net, state = scenario_sumo_files(states_data[0], states_data.root)

    def speeds_after(steps: int) -> dict:
        conn = sumo_start(net, 0, state_file=state)
        for _ in range(steps):
            conn.simulationStep()
        return {v: conn.vehicle.getSpeed(v) for v in conn.vehicle.getIDList()}

    try:
        first = speeds_after(40)
        second = speeds_after(40)  # same process, simulation already advanced and its RNGs used
        assert first == second and len(first) > 5
        conn = sumo_start(net, 0, state_file=state)
        conn.simulation.loadState(str(state))  # what the rollouts used to do: RNGs advanced twice
        for _ in range(40):
            conn.simulationStep()
        assert {v: conn.vehicle.getSpeed(v) for v in conn.vehicle.getIDList()} != first  # why the reload is needed
    finally:
        sumo_close()
