"""SUMO-in-the-loop rollouts for GRPO: the policy drives a scenario's vehicles inside a restored SUMO simulation.

A scenario generated with ``save_states`` (``r1sim generate sumo --save-states``) carries ``metadata["state_file"]``:
a SUMO state saved at the window's *current* index (10 Hz state 10 = boundary pose 2). One rollout:

1. this process's libsumo (one simulation per process) is reloaded with ``-n <net> --step-length 0.1
   --collision.action warn --collision.mingap-factor 0 --collision.check-junctions --time-to-teleport -1
   --seed <sumo_seed> --load-state <state_file>`` before every rollout (a fresh load, not ``simulation.loadState``:
   see :func:`r1sim_sumo.sumo_launch.sumo_start`), so a rollout's SUMO dynamics do not depend on what the worker ran
   before;
2. every scenario agent valid now is handed to the policy (``take_control``: speed mode 32, lane-change mode 0);
   vehicles that enter later (not scenario agents) stay SUMO-driven and react through SUMO's own models;
3. at every 0.5 s decision ``k`` one :func:`r1sim_sumo.rollout.kernel.token_step` (the step of
   :func:`r1sim_sumo.rollout.engine.rollout`, one rollout per simulation) gives logits for all agents; the configured
   sampler draws the token with a ``torch.Generator`` seeded by the rollout seed; the step's SUMO host
   (:class:`_SumoHost`) then places each controlled vehicle every 0.1 s on the token's 10 Hz states
   (:func:`~r1sim_sumo.rollout.kernel.decode_frames`) with ``vehicle.moveToXY`` (front-bumper centre + navigational angle via
   :func:`~r1sim_sumo.adapters.sumo_state.to_sumo_pose`, keepRoute 3);
4. per token step and agent a collision flag: SUMO-reported collisions (``simulation.getCollisions()``, collider or
   victim) OR a separating-axis overlap (:func:`~r1sim_sumo.geometry.boxes_overlap`) with any SUMO-driven vehicle
   (SUMO's lane-based check misses side overlaps), i.e. every vehicle except the policy-controlled ones
   (:func:`sat_obstacle_ids`): scenario agents that enter after the current step are SUMO-driven and checked too.
   Overlaps *between* policy-controlled agents are found by the reward's own SAT
   (:func:`r1sim_sumo.train.rewards.token_collisions`) on the recorded states;
5. an agent SUMO no longer has (arrived, or removed after a failed ``moveToXY``) becomes invalid from the token on
   which it vanished (token -1, pose frozen), as invalid agents do in the in-model engine.

The record is a :class:`~r1sim_sumo.rollout.engine.RolloutResult` (tokens, the sampler's and full-softmax
log-probs, entropy, K_t, boundary poses = the token chain, 10 Hz states reconstructed from the tokens as the engine
does, validity) plus ``extra_collision [G, B, A, F]`` for
:meth:`r1sim_sumo.train.grpo.GRPOLearner.grpo_iteration`. Because moveToXY places the vehicles exactly on the token
chain, the recorded poses are those SUMO simulated (to moveToXY precision) and the teacher-forced recomputation of
the learner sees exactly what the sampling policy saw.

Parallelism: rollouts run in worker processes through :func:`make_rollout_pool` (``r1sim_sumo.workers.make_pool``);
the per-rollout function :func:`run_sumo_rollout_task` is top level and takes a picklable :class:`SumoRolloutTask`. Workers load the policy
from a checkpoint folder once and reload only the weights file when its version changes (:class:`PolicyRef`).

Frames: internal (metres, x east, y north, yaw radians CCW from +x, box centres) except the SUMO calls.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from r1sim_sumo.adapters.sumo_state import read_vehicle_states, take_control, to_sumo_pose
from r1sim_sumo.data.sumo_reference import SumoStateError, scenario_sumo_files, sumo_vehicle_id
from r1sim_sumo.geometry import boxes_overlap
from r1sim_sumo.rollout.engine import N_FUTURE_TOK, RolloutResult
from r1sim_sumo.rollout.kernel import LoopState, StepRecorder, decode_frames, token_step
from r1sim_sumo.sumo_launch import sumo_close, sumo_start
from r1sim_sumo.tokens.constants import CURRENT_POSE, STEPS_PER_TOKEN
from r1sim_sumo.workers import make_pool

KEEP_ROUTE = 3  # moveToXY: exact x,y, mapped onto the vehicle's route (see sim/sumo_controller.py)
DECODING = "central"  # the token's 10 Hz frames, as the in-model engine decodes them (rollout.kernel.decode_frames)


# ---------------------------------------------------------------------------- what a worker receives


@dataclass(frozen=True)
class PolicyRef:
    """Where a worker finds the policy: a checkpoint folder (architecture + vocabulary + initial weights) and
    optionally a safetensors file of the *current* weights (full ``state_dict``) tagged with ``version``."""

    checkpoint: str
    weights: str | None = None
    version: str = ""


@dataclass
class SumoRolloutTask:
    """``len(seeds)`` rollouts of one scene, run one after another in one worker's libsumo.

    :param scene: the :class:`~r1sim_sumo.tokens.batch.TokenizedScene` the learner collates (same agent order).
    :param net_file: the network's ``.net.xml``; ``state_file``: absolute path of the SUMO state at the current index.
    :param seeds: one torch-generator seed per rollout (token sampling).
    :param sampler: sampler spec (``entropy:16,80``, ``topk:32`` ...); ``num_steps``: future tokens (<= 16).
    :param sumo_seed: SUMO ``--seed`` (randomness of the SUMO-driven vehicles).
    :param check_sat: also flag box overlaps with SUMO-driven vehicles (all but the policy-driven ones).
    """

    policy: PolicyRef
    scene: object
    net_file: str
    state_file: str
    seeds: tuple[int, ...]
    sampler: str = "entropy:16,80"
    num_steps: int = N_FUTURE_TOK
    sumo_seed: int = 0
    check_sat: bool = True
    threads: int = 1


@dataclass
class SumoRolloutRecord:
    """Rollouts of one task (numpy), ``g = len(seeds)``, ``A`` the scene's agents, ``F`` token steps.

    token, logp, logp_full, entropy, k, collision ``[g, A, F]``; pose_xy ``[g, A, F+1, 2]``, pose_yaw / valid
    ``[g, A, F+1]``; xy_10hz ``[g, A, 5F+1, 2]``, yaw_10hz ``[g, A, 5F+1]``; sim_mask ``[A]``; counters.
    """

    token: np.ndarray
    logp: np.ndarray
    logp_full: np.ndarray
    entropy: np.ndarray
    k: np.ndarray
    pose_xy: np.ndarray
    pose_yaw: np.ndarray
    valid: np.ndarray
    xy_10hz: np.ndarray
    yaw_10hz: np.ndarray
    collision: np.ndarray
    sim_mask: np.ndarray
    sumo_collisions: int = 0
    sat_collisions: int = 0
    vanished: int = 0
    wall_s: float = 0.0


# ---------------------------------------------------------------------------- per-process state


class _Process:
    """This process's loaded policy (its libsumo session: :func:`r1sim_sumo.sumo_launch.sumo_start`)."""

    policy_key: str | None = None
    weights_version: str | None = None
    policy = None


def _load_policy(ref: PolicyRef):
    if _Process.policy_key != ref.checkpoint:
        from r1sim_sumo.model.checkpoint import load_checkpoint

        _Process.policy = load_checkpoint(ref.checkpoint)
        _Process.policy_key, _Process.weights_version = ref.checkpoint, None
    if ref.weights and _Process.weights_version != ref.version:
        from safetensors.torch import load_file

        _Process.policy.model.load_state_dict(load_file(ref.weights), strict=True)
        _Process.weights_version = ref.version
    return _Process.policy


# ---------------------------------------------------------------------------- one rollout


def sat_obstacle_ids(present_ids, sumo_ids: list[str], controlled) -> list[str]:
    """Vehicles the extra box-overlap check tests the policy-driven agents against: every id in ``present_ids`` (the
    vehicles SUMO has now) except those of ``sumo_ids[a]`` with ``controlled[a]`` true (the policy drives them; their
    mutual overlaps are the reward's). Scenario agents that are not controlled (they enter after the current step,
    or were absent from the state) are SUMO-driven and stay in."""
    mine = {sumo_ids[a] for a in range(len(sumo_ids)) if bool(controlled[a])}
    return [v for v in present_ids if v not in mine]


class _SumoHost:
    """The SUMO side of one in-the-loop rollout, as :func:`~r1sim_sumo.rollout.kernel.token_step`'s ``host``: places
    every driven vehicle on its token's decoded 10 Hz frames (5 ``moveToXY`` + ``simulationStep``), flags collisions and
    reports the agents SUMO no longer has."""

    def __init__(self, conn, sumo_ids: list[str], sim: torch.Tensor, batch, vocab, check_sat: bool):
        self.conn, self.ids, self.sim, self.vocab, self.check_sat = conn, sumo_ids, sim, vocab, check_sat
        self.index_of = {v: a for a, v in enumerate(sumo_ids)}
        self.length = batch.agent_size[0, :, 0].double().numpy()  # [A] [m]
        self.width = batch.agent_size[0, :, 1].double().numpy()
        self.atype = batch.agent_type.long()  # [1, A]
        self.coll = torch.zeros(len(sumo_ids), dtype=torch.bool)
        self.n_sumo = self.n_sat = self.n_gone = 0
        self.decoding = DECODING

    def __call__(self, state: LoopState, tok: torch.Tensor, nxt_valid: torch.Tensor) -> torch.Tensor:
        conn, ids = self.conn, self.ids
        alive = nxt_valid[0].clone()  # [A]
        seg_xy, seg_yaw = decode_frames(state.xy, state.yaw, state.prev, tok, self.vocab, self.atype,
                                        self.decoding)  # [1, A, 6, 2], [1, A, 6]
        self.coll = torch.zeros(len(ids), dtype=torch.bool)
        for j in range(1, STEPS_PER_TOKEN + 1):
            move = torch.nonzero(alive).flatten().tolist()
            fx = seg_xy[0, move, j].double().numpy()
            fyaw = seg_yaw[0, move, j].double().numpy()
            x_fb, y_fb, ang = to_sumo_pose(fx[:, 0], fx[:, 1], fyaw, self.length[move])
            for a, xf, yf, an in zip(move, np.atleast_1d(x_fb).tolist(), np.atleast_1d(y_fb).tolist(),
                                     np.atleast_1d(ang).tolist(), strict=True):
                try:
                    conn.vehicle.moveToXY(ids[a], "", -1, xf, yf, an, KEEP_ROUTE)
                except Exception:  # noqa: BLE001 - no route position near there: the vehicle leaves the rollout
                    alive[a] = False
                    self.n_gone += 1
                    try:
                        conn.vehicle.remove(ids[a])
                    except Exception:  # noqa: BLE001
                        pass
            conn.simulationStep()
            for c in conn.simulation.getCollisions():
                for vid in (c.collider, c.victim):
                    a = self.index_of.get(vid)
                    if a is not None and alive[a]:
                        self.coll[a] = True
                        self.n_sumo += 1
            if self.check_sat:
                self._sat(alive, seg_xy[0, :, j], seg_yaw[0, :, j])
        still = set(conn.vehicle.getIDList())
        for a in torch.nonzero(alive).flatten().tolist():
            if ids[a] not in still:
                alive[a] = False
                self.n_gone += 1
        return alive[None]

    def _sat(self, alive: torch.Tensor, xy: torch.Tensor, yaw: torch.Tensor) -> None:
        """Box overlaps of the driven agents (poses ``xy [A, 2]``, ``yaw [A]``) with every SUMO-driven vehicle."""
        others = sat_obstacle_ids(self.conn.vehicle.getIDList(), self.ids, self.sim)
        mv = torch.nonzero(alive).flatten().numpy()
        if not others or not len(mv):
            return
        st = read_vehicle_states(self.conn, others)
        ax, ay = xy[mv].double().numpy(), yaw[mv].double().numpy()
        length, width = self.length, self.width
        hit = boxes_overlap(ax[:, None, 0], ax[:, None, 1], ay[:, None], length[mv, None], width[mv, None],
                            st.x_m[None], st.y_m[None], st.yaw_rad[None], st.length_m[None], st.width_m[None])  # [n, O]
        hit_a = hit.any(1)
        self.coll[torch.from_numpy(mv[hit_a])] = True
        self.n_sat += int(hit_a.sum())


@torch.no_grad()
def _one_rollout(sumo_key: tuple, model, vocab, batch, sumo_ids: list[str], state_file: str, sampler, seed: int, num_steps: int,
                 check_sat: bool):
    """One SUMO-in-the-loop rollout of a one-scene batch; returns per-agent tensors ``[A, ...]`` and counters."""
    conn = sumo_start(*sumo_key, state_file=state_file)  # fresh RNGs: the rollout does not depend on what ran before
    live0 = (batch.pose_valid[:, :, CURRENT_POSE].bool() & batch.agent_mask.bool())[0]  # [A]
    present = set(conn.vehicle.getIDList())
    sim = live0.clone()
    for a in range(len(sumo_ids)):
        if sim[a] and sumo_ids[a] not in present:
            sim[a] = False  # the state does not hold it (should not happen for a window's agents)
    for a in torch.nonzero(sim).flatten().tolist():
        take_control(conn, sumo_ids[a])
    host = _SumoHost(conn, sumo_ids, sim, batch, vocab, check_sat)
    gen = torch.Generator().manual_seed(int(seed))
    cache = model.init_rollout(batch, num_rollouts=1, upto_step=CURRENT_POSE)
    gt_tok = torch.where(batch.agent_token_valid.bool(), batch.agent_token, -1)
    state = LoopState(gt_tok[:, :, CURRENT_POSE - 1], batch.pose_xy[:, :, CURRENT_POSE], batch.pose_yaw[:, :, CURRENT_POSE],
                      batch.pose_valid[:, :, CURRENT_POSE].bool() & batch.agent_mask.bool())  # [1, A] / [1, A, 2]
    rec, colls = StepRecorder(state), []
    for k in range(CURRENT_POSE, CURRENT_POSE + min(int(num_steps), N_FUTURE_TOK)):
        step = token_step(model, cache, k, state, sampler, gen, vocab, host.atype, sim[None], host=host)
        rec.append(step)
        colls.append(host.coll & sim)
        state = step.state
    out = {f: t[0] for f, t in rec.stack(vocab, host.atype, host.decoding).items()}  # [A, ...]
    out["collision"] = torch.stack(colls, -1)
    return out, sim, (host.n_sumo, host.n_sat, host.n_gone)


def rollout_scene_in_sumo(model, vocab, scene, net_file: str, state_file: str, seeds, sampler="entropy:16,80",
                          num_steps: int = N_FUTURE_TOK, sumo_seed: int = 0, check_sat: bool = True) -> SumoRolloutRecord:
    """``len(seeds)`` SUMO-in-the-loop rollouts of one tokenized scene in *this* process's libsumo.

    :param model: anything with the policy's ``init_rollout`` / ``step`` (e.g. a ``TrafficPolicy`` in eval mode).
    :param scene: :class:`~r1sim_sumo.tokens.batch.TokenizedScene`; ``state_file``: SUMO state at its current index.
    :param sampler: a :class:`~r1sim_sumo.rollout.samplers.Sampler` or its spec string.
    """
    from r1sim_sumo.rollout.samplers import parse_sampler
    from r1sim_sumo.tokens.batch import collate

    t0 = time.perf_counter()
    if not Path(state_file).exists():
        raise SumoStateError(f"state file {state_file} not found; regenerate the dataset with "
                              "`r1sim generate sumo --save-states`")
    batch = collate([scene])
    ids = [sumo_vehicle_id(v) for v in np.asarray(scene.agent_ids).tolist()]
    sampler = parse_sampler(sampler) if isinstance(sampler, str) else sampler
    recs, sim, counts = [], None, np.zeros(3, np.int64)
    for seed in seeds:
        rec, sim, c = _one_rollout((net_file, sumo_seed), model, vocab, batch, ids, state_file, sampler, int(seed), num_steps, check_sat)
        recs.append(rec)
        counts += np.asarray(c)
    stacked = {k: torch.stack([r[k] for r in recs]).numpy() for k in recs[0]}
    return SumoRolloutRecord(**stacked, sim_mask=sim.numpy(), sumo_collisions=int(counts[0]), sat_collisions=int(counts[1]),
                             vanished=int(counts[2]), wall_s=time.perf_counter() - t0)


def run_sumo_rollout_task(task: SumoRolloutTask) -> SumoRolloutRecord:
    """Worker entry point (top level, picklable): load the policy (cached per process) and run ``task``'s rollouts."""
    torch.set_num_threads(max(1, int(task.threads)))
    pol = _load_policy(task.policy)
    return rollout_scene_in_sumo(pol.model.eval(), pol.vocab, task.scene, task.net_file, task.state_file, task.seeds,
                                 task.sampler, task.num_steps, task.sumo_seed, task.check_sat)


# ---------------------------------------------------------------------------- process pool


class _InlinePool:
    """Runs tasks in this process (``workers=0``: tests, debugging)."""

    def map(self, fn, tasks):
        return [fn(t) for t in tasks]

    def close(self) -> None:
        sumo_close()


def make_rollout_pool(workers: int, backend: str = "process"):
    """A pool with ``map(fn, tasks) -> list`` (ordered) and ``close()``; ``workers=0`` runs inline, else
    ``r1sim_sumo.workers.make_pool(backend, workers)``."""
    if workers <= 0:
        return _InlinePool()
    return make_pool(backend, workers)


# ---------------------------------------------------------------------------- the parent side


def assemble(records: list[list[SumoRolloutRecord]], num_agents: int) -> tuple[RolloutResult, torch.Tensor]:
    """Per-scene lists of task records -> ``(RolloutResult [G, B, A, ...], extra_collision [G, B, A, F])``.

    Scenes are padded to ``num_agents`` (the learner's collated batch width): padding agents are invalid.
    """
    B, A = len(records), int(num_agents)
    per_scene = []
    for recs in records:
        cat = {f: np.concatenate([getattr(r, f) for r in recs]) for f in
               ("token", "logp", "logp_full", "entropy", "k", "pose_xy", "pose_yaw", "valid", "xy_10hz", "yaw_10hz", "collision")}
        per_scene.append((cat, recs[0].sim_mask))
    G = per_scene[0][0]["token"].shape[0]
    if any(c["token"].shape[0] != G for c, _ in per_scene):
        raise ValueError("assemble: scenes have different numbers of rollouts")

    def pad(f: str, fill) -> torch.Tensor:
        arrs = []
        for c, _ in per_scene:
            a = c[f]
            out = np.full((G, A, *a.shape[2:]), fill, dtype=a.dtype)
            out[:, : a.shape[1]] = a
            arrs.append(out)
        return torch.from_numpy(np.stack(arrs, 1))  # [G, B, A, ...]

    sim = np.zeros((B, A), bool)
    for b, (_, s) in enumerate(per_scene):
        sim[b, : len(s)] = s
    res = RolloutResult(
        token=pad("token", -1).long(), logp=pad("logp", 0).float(), logp_full=pad("logp_full", 0).float(),
        entropy=pad("entropy", 0).float(), k=pad("k", 0).long(), pose_xy=pad("pose_xy", 0).float(),
        pose_yaw=pad("pose_yaw", 0).float(), xy_10hz=pad("xy_10hz", 0).float(), yaw_10hz=pad("yaw_10hz", 0).float(),
        valid=pad("valid", False).bool(), sim_mask=torch.from_numpy(sim),
    )
    return res, pad("collision", False).bool()


class SumoRolloutSource:
    """Runs GRPO's rollout groups in SUMO worker processes.

    :param scenarios: the :class:`~r1sim_sumo.scenario.ScenarioDataset` (generated with ``save_states``) whose
        scenes the learner's batches come from (same indices).
    :param workers: worker processes (0 = in this process); ``backend`` for ``r1sim_sumo.workers.make_pool``. Records
        do not depend on the worker count, the backend or how tasks are sharded: every rollout reloads SUMO from
        its state file (:func:`sumo_start`).
    :param sumo_seed: SUMO ``--seed`` of every rollout (common random numbers inside a group).
    :param check_sat: also flag box overlaps with SUMO-driven vehicles.
    :param tasks_per_worker: rollout chunks per worker and iteration (load balance vs per-task overhead).
    """

    def __init__(self, scenarios, workers: int = 2, backend: str = "process", sumo_seed: int = 0, check_sat: bool = True,
                 tasks_per_worker: int = 2):
        self.scenarios = scenarios
        self.root = Path(getattr(scenarios, "root", "."))
        self.workers = int(workers)
        self.sumo_seed = int(sumo_seed)
        self.check_sat = bool(check_sat)
        self.tasks_per_worker = max(1, int(tasks_per_worker))
        self.pool = make_rollout_pool(self.workers, backend)
        self.last_stats: dict = {}

    def close(self) -> None:
        self.pool.close()

    def __enter__(self) -> SumoRolloutSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def rollout(self, policy: PolicyRef, indices: list[int], scenes: list, num_rollouts: int, sampler: str,
                generator: torch.Generator, num_steps: int = N_FUTURE_TOK) -> tuple[RolloutResult, torch.Tensor]:
        """``num_rollouts`` SUMO-in-the-loop rollouts of each scene ``scenes[b]`` (= scenario ``indices[b]``).

        Rollout seeds are drawn from ``generator`` (``[B, G]`` int64), so a run is reproducible whatever the
        worker count. Returns ``(RolloutResult [G, B, A, ...], extra_collision [G, B, A, F])`` with ``A`` the widest
        scene (as :func:`~r1sim_sumo.tokens.batch.collate` pads).
        """
        t0 = time.perf_counter()
        G, B = int(num_rollouts), len(indices)
        seeds = torch.randint(0, 2**62, (B, G), generator=generator).tolist()
        n_chunks = max(1, min(G, math.ceil(max(self.workers, 1) * self.tasks_per_worker / B)))
        tasks, owner = [], []
        for b, (i, scene) in enumerate(zip(indices, scenes, strict=True)):
            net, state = scenario_sumo_files(self.scenarios[i], self.root, where=f"{self.root} scenario {i}")
            for ch in np.array_split(np.arange(G), n_chunks):
                if len(ch):
                    tasks.append(SumoRolloutTask(policy, scene, net, state, tuple(seeds[b][j] for j in ch), sampler,
                                                 num_steps, self.sumo_seed, self.check_sat))
                    owner.append(b)
        outs = self.pool.map(run_sumo_rollout_task, tasks)
        per_scene: list[list[SumoRolloutRecord]] = [[] for _ in range(B)]
        for b, r in zip(owner, outs, strict=True):
            per_scene[b].append(r)
        A = max(int(s.agents.num_agents) for s in scenes)
        res, extra = assemble(per_scene, max(A, 1))
        self.last_stats = {
            "sumo_collisions": sum(r.sumo_collisions for r in outs), "sat_collisions": sum(r.sat_collisions for r in outs),
            "vanished": sum(r.vanished for r in outs), "worker_s": sum(r.wall_s for r in outs),
            "rollout_s": time.perf_counter() - t0, "tasks": len(tasks),
        }
        return res, extra


class SumoInLoop:
    """GRPO fine-tuning with SUMO-in-the-loop rollouts (``rollout_source: sumo`` of :class:`GRPOConfig`).

    Publishes the learner's current weights to ``work_dir`` each iteration (a base checkpoint once, then a
    safetensors ``state_dict`` with a version tag the workers compare) and runs the group in workers.
    """

    def __init__(self, cfg, model, vocab, scenarios, work_dir: str | os.PathLike, workers: int = 2):
        from r1sim_sumo.model.checkpoint import save_checkpoint

        if cfg.method == "sft":
            raise ValueError("rollout_source=sumo: closed-loop SFT (method: sft) rolls out in the model; use method grpo or grpo-std")
        self.cfg = cfg
        self.work = Path(work_dir)
        self.work.mkdir(parents=True, exist_ok=True)
        self.base = save_checkpoint(self.work / "base", model, vocab, extra={"purpose": "SUMO-in-the-loop worker base"})
        self.weights = self.work / "weights.safetensors"
        self.source = SumoRolloutSource(scenarios, workers=workers, backend=getattr(cfg, "sumo_backend", "process"),
                                        sumo_seed=cfg.seed)

    def publish(self, model, version: str) -> PolicyRef:
        """Write ``model``'s weights atomically and return the reference workers load them from."""
        from safetensors.torch import save_file

        tmp = self.weights.with_suffix(".tmp")
        save_file({k: v.detach().contiguous() for k, v in model.state_dict().items()}, str(tmp))
        os.replace(tmp, self.weights)
        return PolicyRef(str(self.base), str(self.weights), version)

    def iteration(self, learner, indices: list[int], scenes: list, batch, generator: torch.Generator, it: int,
                  maps=None) -> dict:
        """One GRPO iteration: rollouts in SUMO, then :meth:`GRPOLearner.grpo_iteration` on them."""
        cfg = self.cfg
        ref = self.publish(learner.model, f"iter-{it}")
        res, extra = self.source.rollout(ref, indices, scenes, cfg.num_rollouts, cfg.sampler, generator, cfg.num_steps)
        st = learner.grpo_iteration(batch, generator, result=res, extra_collision=extra, maps=maps)
        st["rollout_s"] = self.source.last_stats["rollout_s"]
        st["sumo_collision_rate"] = float(extra.sum() / ((res.token >= 0) & res.sim_mask[None, :, :, None]).sum().clamp(min=1))
        return st

    def close(self) -> None:
        self.source.close()
