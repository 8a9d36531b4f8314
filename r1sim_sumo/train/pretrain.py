"""Next-token-prediction pretraining of the traffic policy (``r1sim pretrain --config configs/pretrain.yaml``).

Loop: tokenized scenes (rolling-matched motion tokens + map tokens) -> teacher-forced logits over all 18 token
steps -> label-smoothed cross-entropy on valid tokens; AdamW with linear warm-up then cosine decay; random
history-token drop (an agent's first history token hidden from the input with probability
``history_drop_prob``); progress bar with loss / accuracy; CSV log (``log.csv``); periodic training-state
checkpoints (``state/``) from which ``--resume`` continues with the same subsequent steps; the final policy is
exported as a checkpoint folder (``final/``: safetensors + JSON, loadable by :func:`r1sim_sumo.load_policy`).

Determinism: the scene order of epoch ``e`` is a permutation drawn from ``seed + e``; every step re-seeds
torch with ``seed * 1_000_003 + step`` so dropout and history drop do not depend on what ran before. With
``num_workers=0`` on CPU a run and a killed-then-resumed run produce identical weights.

Data parallel: launched by ``torchrun --nproc_per_node N -m r1sim_sumo.cli pretrain ...`` every rank builds
the same global batch of ``batch_size`` scenes and trains on its slice (:mod:`r1sim_sumo.train.ddp`); the
loss is the mean over all valid tokens of the global batch, as in one process. Only rank 0 writes.
"""

from __future__ import annotations

import csv
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from r1sim_sumo._memory import keep_freed_memory
from r1sim_sumo.config import load_config, save_config
from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.model.packed import loss_mask, packed_loss, reach_radius_m
from r1sim_sumo.model.policy import token_nll_and_correct
from r1sim_sumo.tokens.batch import collate, crop_map_to_reach
from r1sim_sumo.tokens.constants import CURRENT_POSE, N_TOK
from r1sim_sumo.tokens.matching import speed_band
from r1sim_sumo.train.steady_history import steady_history, straight_token_table


@dataclass
class PretrainConfig:
    train_data: str = "data/generated/default/train"  # dataset folder (manifest.json + shards)
    val_data: str | None = "data/generated/default/val"
    vocab: str | None = None  # vocabulary file; None = build from train_data into out_dir/vocab.safetensors
    vocab_size: int = 2048  # vehicle vocabulary size when building
    model: str = "nano"  # preset name
    model_overrides: dict = field(default_factory=dict)
    batch_size: int = 16  # scenes per step
    max_steps: int = 2000
    lr: float = 1e-3
    weight_decay: float = 0.05
    warmup_steps: int = 100
    min_lr_ratio: float = 0.05
    label_smoothing: float = 0.1
    history_drop_prob: float = 0.1
    prev_token_drop_prob: float = 0.0  # fast path: hide the previous-token input of this share of nodes (labels kept), against token copying
    steady_history_prob: float = 0.0  # show this share of speeding-up vehicles a steady-speed past (r1sim_sumo.train.steady_history), against copying a low speed on a free road
    steady_history_min_run: int = 1  # ... only where the speed-up lasts this many tokens (2: not a one-token fluctuation)
    desired_speed_drop_prob: float = 0.0  # hide each agent's desired speed (model input desired_speed_input) with this probability, so the model also drives when a host does not know it
    token_noise_top_k: int = 1  # 1: exact matching; > 1: noised rolling matching of training scenes (SMART), see match_agents
    token_noise_speed_tol_mps: float | list[float] | None = None  # noised matching draws only tokens within this many m/s of the nearest one's mean speed (noise that keeps the speed trend, see match_agents), or within [below, above] m/s of it ([1.0, 0.0]: slower-only); None: free noise
    grad_clip: float = 1.0
    seed: int = 0
    threads: int = 1  # CPU threads of this run: one run per core (two runs side by side beat one run on two threads)
    loader_workers: int = 0  # CPU processes that build the next batches (noised matching, map crop, collate) while the model trains; 0: in the training process. Same batches for any value; on a GPU the batches, not the model, set the pace (~30 ms of CPU per scene)
    fast: bool = True  # packed training forward (real map tokens and valid nodes only) on reach-cropped maps; same loss as the padded forward
    precision: str = "fp32"  # "bf16": autocast of the forward (loss and optimizer in fp32; for GPUs: slower than fp32 on the 2-core CPU); "fp32"
    device: str = "cpu"  # "cpu", "cuda", "cuda:N" or "auto" (cuda when available)
    tokens: str | None = None  # compact token dataset folder (`r1sim tokens build`); replaces train_data / val_data / vocab
    extra_tokens: list[str] = field(default_factory=list)  # more compact datasets whose train splits join `tokens`' (same vocabulary); validation stays on `tokens`' val split
    val_tokens: str | None = None  # a compact dataset whose val split is evaluated instead of `tokens`' (same vocabulary)
    ending_lane_lr_mult: float = 1.0  # != 1: the ending-lane kind's embedding row (map kind 2) trains at lr x this without weight decay, the other kinds' rows stay frozen (a new row learns in hundreds of steps, not tens of thousands)
    init_checkpoint: str | None = None  # start from these weights (a checkpoint folder, e.g. the shipped r1sim-nano); fresh optimizer
    log_every: int = 10
    eval_every: int = 500
    eval_batches: int = 20
    ckpt_every: int = 200
    keep_every: int = 0  # also export a checkpoint folder ckpt-XXXXXX every this many steps (0: none), for learning curves
    out_dir: str = "runs/pretrain"
    token_cache: str | None = None  # folder for the precomputed tokenized-scene cache (default: out_dir/token_cache)
    shard_cache: int = 128  # decompressed scenario shards kept in memory (random access touches all of them)

    def __post_init__(self) -> None:
        from r1sim_sumo.config import ConfigError
        from r1sim_sumo.model.config import PolicyConfig
        from r1sim_sumo.tokens.matching import PREFILTER_K

        if self.precision not in ("fp32", "bf16"):
            raise ConfigError(f"key 'precision': {self.precision!r} must be 'fp32' or 'bf16'")
        if not (self.device in ("cpu", "cuda", "auto") or str(self.device).startswith("cuda:")):
            raise ConfigError(f"key 'device': {self.device!r} must be 'cpu', 'cuda', 'cuda:N' or 'auto'")
        if not 0.0 <= float(self.prev_token_drop_prob) < 1.0:
            raise ConfigError(f"key 'prev_token_drop_prob': {self.prev_token_drop_prob} must be in [0, 1)")
        if self.prev_token_drop_prob > 0 and not self.fast:
            raise ConfigError("key 'prev_token_drop_prob': needs fast: true (the packed training forward)")
        if not float(self.ending_lane_lr_mult) > 0:
            raise ConfigError(f"key 'ending_lane_lr_mult': {self.ending_lane_lr_mult} must be > 0 (1 = no separate rate)")
        if not 0.0 <= float(self.steady_history_prob) <= 1.0:
            raise ConfigError(f"key 'steady_history_prob': {self.steady_history_prob} must be in [0, 1]")
        if int(self.steady_history_min_run) < 1:
            raise ConfigError(f"key 'steady_history_min_run': {self.steady_history_min_run} must be >= 1 (1 = any speed-up)")
        if not 0.0 <= float(self.desired_speed_drop_prob) < 1.0:
            raise ConfigError(f"key 'desired_speed_drop_prob': {self.desired_speed_drop_prob} must be in [0, 1)")
        if int(self.loader_workers) < 0:
            raise ConfigError(f"key 'loader_workers': {self.loader_workers} must be >= 0 (0: batches built in the training process)")
        if int(self.threads) < 1:
            raise ConfigError(f"key 'threads': {self.threads} must be >= 1")
        for key in ("eval_every", "log_every", "ckpt_every"):  # steps between evaluations / log lines / checkpoints
            if int(getattr(self, key)) < 1:
                raise ConfigError(f"key '{key}': {getattr(self, key)} must be >= 1 (steps); to do it only at the end, "
                                  f"set it to max_steps ({self.max_steps})")
        if int(self.keep_every) < 0:
            raise ConfigError(f"key 'keep_every': {self.keep_every} must be >= 0 (0: no kept checkpoint folders)")
        if not 1 <= int(self.token_noise_top_k) <= PREFILTER_K:
            raise ConfigError(f"key 'token_noise_top_k': {self.token_noise_top_k} must be in 1..{PREFILTER_K} "
                              "(1 = exact matching, 5 = SMART-style noise)")
        if self.token_noise_speed_tol_mps is not None:
            try:
                speed_band(self.token_noise_speed_tol_mps)
            except (TypeError, ValueError):
                raise ConfigError(f"key 'token_noise_speed_tol_mps': {self.token_noise_speed_tol_mps!r} must be a number "
                                  ">= 0 [m/s], a pair [below, above] of them, or null (free noise)") from None
        # fail at load time (naming the key), not after the vocabulary and token cache are built
        try:
            PolicyConfig.preset(self.model, **{k: v for k, v in self.model_overrides.items() if k != "vocab_sizes"})
        except ConfigError as exc:
            raise ConfigError(f"key 'model' / 'model_overrides': {exc}") from exc


def lr_at(step: int, cfg: PretrainConfig) -> float:
    """Linear warm-up to ``lr`` over ``warmup_steps``, then cosine to ``lr * min_lr_ratio`` at ``max_steps``."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    t = min(1.0, (step - cfg.warmup_steps) / max(1, cfg.max_steps - cfg.warmup_steps))
    return cfg.lr * (cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * t)))


class EpochBatches:
    """Deterministic batches: global step -> list of scene indices (epoch permutation from ``seed + epoch``)."""

    def __init__(self, n: int, batch_size: int, seed: int):
        if n == 0:
            raise ValueError("training dataset is empty")
        self.n, self.bs, self.seed = n, min(batch_size, n), seed
        self.per_epoch = max(1, n // self.bs)
        self._perm_epoch, self._perm = -1, None

    def __call__(self, step: int) -> list[int]:
        epoch, b = divmod(step, self.per_epoch)
        if epoch != self._perm_epoch:
            self._perm = np.random.default_rng(self.seed + epoch).permutation(self.n)
            self._perm_epoch = epoch
        return self._perm[b * self.bs : (b + 1) * self.bs].tolist()


class StepBatches(torch.utils.data.Dataset):
    """Global step -> that step's training input, built on the CPU from ``(seed, step)`` alone, so that a resumed run,
    and a run whose batches are built ahead by ``loader_workers`` processes, sees exactly the same batches.

    An item is ``(batch, targets, gen_state)``: the collated (reach-cropped with ``fast``) scenes after history and
    desired-speed dropping, the noised-matching labels (None without noise), and the state of the step's generator
    after those draws (the training process draws the previous-token mask from it after sharding).
    """

    def __init__(self, cfg: PretrainConfig, train_ds, reach_m: float, vocab=None):
        self.cfg, self.ds, self.reach_m = cfg, train_ds, reach_m
        self.batches = EpochBatches(len(train_ds), cfg.batch_size, cfg.seed)
        self.straight = None
        if cfg.steady_history_prob > 0:
            if vocab is None:
                raise ValueError("StepBatches: steady_history_prob > 0 needs the motion vocabulary")
            self.straight = straight_token_table(vocab.traj[0])

    def __len__(self) -> int:
        return self.cfg.max_steps

    def __getitem__(self, step: int):
        cfg = self.cfg
        gen = torch.Generator().manual_seed(cfg.seed * 7_919 + step)
        if cfg.token_noise_top_k > 1:  # re-matched every draw; the noise depends on (seed, step, scene) only
            tol = None if cfg.token_noise_speed_tol_mps is None else speed_band(cfg.token_noise_speed_tol_mps)
            scenes = [self.ds.noised(i, cfg.token_noise_top_k, np.random.default_rng([cfg.seed, step, i]), tol)
                      for i in self.batches(step)]
        else:
            scenes = [self.ds[i] for i in self.batches(step)]
        if cfg.fast:  # map tokens no agent node can reach change no logit
            scenes = [crop_map_to_reach(sc, self.reach_m) for sc in scenes]
        batch = collate(scenes)
        has_labels = cfg.token_noise_top_k > 1 or any(sc.agents.target is not None for sc in scenes)
        targets = collate_targets(scenes, batch) if has_labels else None
        batch, targets = steady_history(batch, targets, cfg.steady_history_prob, gen, self.straight,
                                            min_run=cfg.steady_history_min_run)
        batch = drop_history(batch, cfg.history_drop_prob, gen)
        batch = drop_desired_speed(batch, cfg.desired_speed_drop_prob, gen)
        return batch, targets, gen.get_state()


def _one_thread_worker(_worker_id: int) -> None:
    torch.set_num_threads(1)


def step_inputs(step_batches: StepBatches, first_step: int, workers: int):
    """Iterate ``step_batches[first_step:]``: in this process (``workers`` 0) or built ahead by ``workers`` processes."""
    steps = range(first_step, len(step_batches))
    if workers == 0:
        return (step_batches[s] for s in steps)
    return iter(torch.utils.data.DataLoader(
        step_batches, batch_size=None, sampler=steps, num_workers=workers, collate_fn=_identity,
        worker_init_fn=_one_thread_worker, prefetch_factor=4, multiprocessing_context="fork"))


def _identity(item):
    return item


def collate_targets(scenes, batch) -> torch.Tensor:
    """The labels (``agents.target``: noised matching, masked history; else ``agents.token``) of ``scenes``, padded like ``collate`` pads tokens: ``[B, A, n_tok]``."""
    out = torch.full_like(batch.agent_token, -1)
    for b, s in enumerate(scenes):  # a scene without separate labels is labelled by its own tokens
        lab = s.agents.target if s.agents.target is not None else s.agents.token
        out[b, : s.agents.num_agents] = torch.from_numpy(np.asarray(lab, np.int64))
    return out


def drop_history(batch, prob: float, gen: torch.Generator):
    """Hide each agent's first history token from the input with probability ``prob`` (SMART-style)."""
    if prob <= 0:
        return batch
    B, A = batch.agent_mask.shape
    drop = torch.rand(B, A, generator=gen) < prob  # [B, A]
    tv = batch.agent_token_valid.clone()
    tv[..., 0] &= ~drop
    return batch._replace(agent_token_valid=tv)


def drop_desired_speed(batch, prob: float, gen: torch.Generator):
    """Mark each agent's desired speed unknown (NaN) with probability ``prob``; draws nothing when ``prob`` is 0."""
    if prob <= 0:
        return batch
    drop = torch.rand(batch.agent_mask.shape, generator=gen) < prob  # [B, A]
    return batch._replace(agent_desired_speed=batch.agent_desired_speed.masked_fill(drop, float("nan")))


def ending_lane_row(model, cfg: PretrainConfig):
    """With ``cfg.ending_lane_lr_mult != 1``: the map-kind embedding ``[num_map_kinds, D]``, its gradient masked to
    the ending lane's row (``tokens.map_tokens.ENDING_LANE``) so that the other kinds' rows stay as they are; the
    caller gives it its own optimizer group (lr x the multiplier, no weight decay). None otherwise."""
    from r1sim_sumo.config import ConfigError
    from r1sim_sumo.tokens.map_tokens import ENDING_LANE

    if cfg.ending_lane_lr_mult == 1.0:
        return None
    if model.config.num_map_kinds <= ENDING_LANE:
        raise ConfigError(f"key 'ending_lane_lr_mult': the model tells {model.config.num_map_kinds} map kinds apart, "
                          f"the ending lane is kind {ENDING_LANE}; set model_overrides: {{num_map_kinds: 3}}")
    w = model.map_kind.weight
    keep = torch.zeros(w.shape[0], 1, dtype=w.dtype, device=w.device)
    keep[ENDING_LANE] = 1.0
    w.register_hook(lambda g: g * keep.to(g.device))
    return w


NEIGHBOUR_RADII = ("map_radius_m", "map_agent_radius_m", "agent_radius_m")  # [m] kNN search radii of PolicyConfig


def load_init_weights(model, init, source: str) -> list[str]:
    """Copy ``init``'s weights into ``model``. The two configs must be equal except that ``model`` may add the
    desired-speed, speed-gap and speed-trend inputs (their embeddings start at zero output, so the logits start equal to
    ``init``'s) and may tell more map token kinds apart (``num_map_kinds``: each new kind's embedding row starts as a
    copy of the lane centre's, which is how ``init`` reads those tokens, so the logits start equal too), and may search
    its neighbours within other radii (:data:`NEIGHBOUR_RADII`: they only choose which k nearest nodes attend, no
    weight depends on them). Returns the names of the new parameters."""
    mine, theirs = model.config.to_dict(), init.config.to_dict()
    theirs.update({k: mine[k] for k in NEIGHBOUR_RADII if k in mine})
    inputs = {"desired_speed_input": "desired_speed_emb.", "speed_gap_input": "speed_gap_emb.",
              "speed_trend_input": "speed_trend_emb."}  # zero-output at the start
    added = [k for k in inputs if mine.get(k) and not theirs.get(k)]
    theirs = {**theirs, **{k: True for k in added}}
    state = dict(init.model.state_dict())
    old_kinds, new_kinds = theirs.get("num_map_kinds", 2), mine.get("num_map_kinds", 2)
    if new_kinds > old_kinds:  # new map kinds read as the lane centre (row 0) did
        w = state["map_kind.weight"]
        state["map_kind.weight"] = torch.cat([w, w[:1].expand(new_kinds - old_kinds, -1)], 0).clone()
        theirs["num_map_kinds"] = new_kinds
    if theirs != mine:
        raise ValueError(f"key 'init_checkpoint': {source} holds a model {init.config.to_dict()} but the run "
                         f"configures {model.config.to_dict()}; set 'model'/'model_overrides' to match")
    res = model.load_state_dict(state, strict=not added)
    if res.unexpected_keys or any(not k.startswith(tuple(inputs[a] for a in added)) for k in res.missing_keys):
        raise ValueError(f"key 'init_checkpoint': {source} does not fit the run's model (missing {res.missing_keys}, "
                         f"unexpected {res.unexpected_keys})")
    return list(res.missing_keys)


def _build_or_load_vocab(cfg: PretrainConfig, out: Path):
    from r1sim_sumo.scenario import ScenarioDataset
    from r1sim_sumo.tokens.motion_vocab import MotionVocab, VocabBuildConfig
    from r1sim_sumo.tokens.vocab_build import build_vocab_from_dataset

    if cfg.vocab:
        return MotionVocab.load(cfg.vocab)
    if cfg.init_checkpoint:  # the vocabulary the initial weights were trained with
        return load_policy(cfg.init_checkpoint).vocab
    path = out / "vocab.safetensors"
    if path.exists():
        return MotionVocab.load(path)
    vcfg = VocabBuildConfig(size=(cfg.vocab_size, 512, 512), seed=cfg.seed)
    vocab, report = build_vocab_from_dataset(ScenarioDataset(cfg.train_data), vcfg, progress=True)
    vocab.save(path)
    (out / "vocab_report.json").write_text(json.dumps(report, indent=2, default=float))
    return vocab


def resolve_device(name: str) -> torch.device:
    """``"auto"`` -> CUDA when available, else CPU; ``"cuda"`` without a GPU is an error naming the key."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"key 'device': {name!r} but torch sees no CUDA device (torch {torch.__version__}); "
                           "use device: cpu, or install a CUDA build of torch")
    return dev


def autocast(device: torch.device, precision: str):
    """bf16 autocast of the forward on ``device`` (``precision="bf16"``), a no-op context for ``"fp32"``."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16")


@torch.no_grad()
def evaluate_nll(model, dataset, collate_fn, batch_size: int, max_batches: int | None = None,
                 device: torch.device | str = "cpu", packed: bool = True) -> dict:
    """Held-out next-token NLL [nats] and top-1 accuracy over valid future tokens (no label smoothing), fp32.
    ``packed``: logits from the packed forward (same values as the padded one, less work)."""
    model.eval()
    tot_nll, tot_ok, tot_n = 0.0, 0, 0
    nb = math.ceil(len(dataset) / batch_size)
    starts = [b * batch_size for b in range(nb)]
    if max_batches and max_batches < nb:  # evenly spread over the split (all networks), not its first scenes
        starts = [starts[int(j)] for j in np.linspace(0, nb - 1, max_batches).round()]
    for b0 in starts:
        items = [dataset[i] for i in range(b0, min(len(dataset), b0 + batch_size))]
        batch = collate_fn(items).to(device)
        if packed:
            rows = loss_mask(batch)
            rows[:, :, :CURRENT_POSE] = False  # future tokens only
            logits = model(batch, out_mask=rows)
            target = batch.agent_token[rows]
            nll = float(-torch.log_softmax(logits.float(), -1).gather(-1, target.unsqueeze(-1)).sum())
            ok, n = int((logits.argmax(-1) == target).sum()), int(target.numel())
        else:
            nll, ok, n = token_nll_and_correct(batch, model(batch))
        tot_nll += float(nll)
        tot_ok += int(ok)
        tot_n += int(n)
    model.train()
    return {"nll": tot_nll / max(tot_n, 1), "top1": tot_ok / max(tot_n, 1), "tokens": tot_n}


INIT_FILE = "init.json"  # in a run folder: the starting checkpoint and the SHA-256 of its weights file


def record_init(out: Path, checkpoint: str, weights_sha256: str | None) -> None:
    """Write ``out/init.json`` ``{"init_checkpoint", "weights_sha256"}`` when a run starts from a checkpoint, so that
    a bundled name (``r1sim-nano``), which a later ship replaces, still says which weights the run started from."""
    (Path(out) / INIT_FILE).write_text(json.dumps({"init_checkpoint": checkpoint, "weights_sha256": weights_sha256}, indent=1) + "\n")


def recorded_init(run: Path) -> dict:
    """``init.json`` of a run folder (``{}`` when the run recorded none)."""
    f = Path(run) / INIT_FILE
    return json.loads(f.read_text()) if f.is_file() else {}


def _train_info(cfg: PretrainConfig, step: int, seen: dict) -> dict:
    info = {"steps": step, "agent_tokens_seen": int(seen["agent_tokens"]), "cpu_hours": seen["cpu_s"] / 3600.0,
            "init_checkpoint": cfg.init_checkpoint, "config": asdict(cfg)}
    dev = resolve_device(cfg.device)
    if dev.type == "cuda":  # the model card names the machine that trained (the CPU hours count the main process only)
        info["device_name"] = torch.cuda.get_device_name(dev)
    return info


def write_run_state(out: Path, cfg: PretrainConfig, step: int, seen: dict) -> None:
    """``run_state.json``: where a run stands and the command that continues it (small; commit it with ``state/``)."""
    state = {"step": step, "max_steps": cfg.max_steps, "agent_tokens_seen": int(seen["agent_tokens"]),
             "cpu_hours": round(seen["cpu_s"] / 3600.0, 4),
             "resume": f"r1sim pretrain --config {out / 'config.yaml'} --resume",
             "needs": "the training state folder state/ (weights + optimizer) and the data the config names "
                      f"({', '.join(dict.fromkeys([cfg.tokens or cfg.train_data, *cfg.extra_tokens]))})"}
    tmp = out / "run_state.json.tmp"
    tmp.write_text(json.dumps(state, indent=1))
    os.replace(tmp, out / "run_state.json")


def training_datasets(cfg: PretrainConfig, out: Path):
    """``(vocab, train, val)``: from the compact token dataset (``cfg.tokens``) or from scenario folders tokenized
    on the fly into ``token_cache`` (val is None without ``val_data``). Both give :class:`TokenizedScene` items
    and ``noised(i, k, rng)``."""
    from r1sim_sumo.scenario import ScenarioDataset
    from r1sim_sumo.tokens.batch import TokenizedDataset
    from r1sim_sumo.tokens.compact import CompactTokenDataset, JoinedTokenDatasets

    if cfg.extra_tokens and not cfg.tokens:
        raise ValueError("key 'extra_tokens': needs 'tokens' (the main compact dataset, whose val split is evaluated)")
    if cfg.tokens:
        val_root = cfg.val_tokens or cfg.tokens
        if cfg.val_tokens and not CompactTokenDataset.has_split(val_root, "val"):
            raise ValueError(f"key 'val_tokens': {val_root} has no val split; build it with `r1sim tokens build "
                             f"--data <dataset folder> --out {val_root} --splits val`")
        train = CompactTokenDataset(cfg.tokens, "train")
        val = CompactTokenDataset(val_root, "val") if CompactTokenDataset.has_split(val_root, "val") else None
        if val is not None and val.vocab.fingerprint() != train.vocab.fingerprint():
            raise ValueError(f"key 'val_tokens': {val_root} was built with another vocabulary than {cfg.tokens}; "
                             "rebuild it with `--vocab` set to the train dataset's vocab.safetensors")
        if cfg.extra_tokens:
            train = JoinedTokenDatasets([train, *(CompactTokenDataset(p, "train") for p in cfg.extra_tokens)])
        return train.vocab, train, val
    vocab = _build_or_load_vocab(cfg, out)
    cache = Path(cfg.token_cache) if cfg.token_cache else out / "token_cache"
    # random batches touch every shard: keep decompressed shards in memory (about 50 MB per 256-scene shard)
    train = TokenizedDataset(ScenarioDataset(cfg.train_data, cache_shards=cfg.shard_cache), vocab, cache_dir=cache / "train")
    val = TokenizedDataset(ScenarioDataset(cfg.val_data, cache_shards=cfg.shard_cache), vocab, cache_dir=cache / "val") if cfg.val_data else None
    return vocab, train, val


def pretrain(cfg: PretrainConfig, resume: bool = False, progress: bool = True, stop_at_step: int | None = None) -> Path | None:
    """Run (or resume) pretraining; returns the exported checkpoint folder ``out_dir/final``.

    ``stop_at_step`` simulates an interruption (fault injection): the run returns ``None`` right after step
    ``stop_at_step`` without exporting, leaving only what a killed run leaves (the last periodic state).
    """
    from tqdm import tqdm

    from r1sim_sumo.model.checkpoint import save_checkpoint
    from r1sim_sumo.model.config import PolicyConfig
    from r1sim_sumo.model.policy import TrafficPolicy
    from r1sim_sumo.train import ddp
    from r1sim_sumo.train.train_state import load_train_state, save_train_state

    torch.set_num_threads(cfg.threads)
    keep_freed_memory()  # reuse freed temporaries instead of zero-filling fresh pages every step
    device = resolve_device(cfg.device)
    dinfo = ddp.init_from_env(str(device))  # one process unless launched by torchrun
    out = Path(cfg.out_dir)
    state_dir = out / "state"
    if out.exists() and (state_dir / "state.json").exists() and not resume:
        raise FileExistsError(f"{out} holds a training run; pass --resume to continue it or choose another out_dir")
    if not dinfo.is_main:
        ddp.barrier(dinfo)  # rank 0 writes the config, vocabulary and token-cache folders first
    out.mkdir(parents=True, exist_ok=True)
    if dinfo.is_main:
        save_config(cfg, out / "config.yaml")

    vocab, train_ds, val_ds = training_datasets(cfg, out)
    if dinfo.is_main:
        ddp.barrier(dinfo)

    torch.manual_seed(cfg.seed)
    mcfg = PolicyConfig.preset(cfg.model, **{"vocab_sizes": vocab.sizes, **cfg.model_overrides})
    model = TrafficPolicy(mcfg, [torch.as_tensor(vocab.traj[t]) for t in range(3)])
    if cfg.init_checkpoint and not resume:
        init = load_policy(cfg.init_checkpoint)  # a checkpoint folder or a bundled name ("r1sim-nano")
        if init.vocab.fingerprint() != vocab.fingerprint():
            raise ValueError(f"key 'init_checkpoint': {cfg.init_checkpoint} was trained with another vocabulary than "
                             "the run's; leave 'vocab' unset to use the checkpoint's")
        load_init_weights(model, init, cfg.init_checkpoint)
        if dinfo.is_main:  # which weights a bundled name meant when the run started (it may be re-shipped later)
            record_init(out, cfg.init_checkpoint, init.info.get("weights", {}).get("sha256"))
    model.to(device)
    reach_m = reach_radius_m(mcfg) + 1.0  # [m] 1 m margin over the exact receptive field
    kind_row = ending_lane_row(model, cfg)  # the map-kind embedding, trained apart (or None)
    decay = [p for n, p in model.named_parameters() if p.dim() >= 2 and p is not kind_row]
    no_decay = [p for n, p in model.named_parameters() if p.dim() < 2]
    groups = [{"params": decay, "weight_decay": cfg.weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
    if kind_row is not None:
        groups.append({"params": [kind_row], "weight_decay": 0.0, "lr_mult": float(cfg.ending_lane_lr_mult)})
    opt = torch.optim.AdamW(groups, lr=cfg.lr)
    step = 0
    seen = {"agent_tokens": 0, "cpu_s": 0.0}  # of this run (resumed runs continue the counts)
    if resume and ((state_dir / "state.json").exists() or state_dir.with_name("state.old").exists()):
        info = load_train_state(state_dir, model, opt)
        step = int(info["step"])
        seen.update(info.get("seen", {}))
        print(f"[pretrain] resumed from {state_dir} at step {step}")
    fwd = ddp.wrap_model(model, dinfo)  # DistributedDataParallel when distributed; `model` stays the bare module

    inputs = step_inputs(StepBatches(cfg, train_ds, reach_m, vocab), step, int(cfg.loader_workers))
    log_path = out / "log.csv"
    log_fields = ["step", "lr", "loss", "acc", "tokens_per_s", "val_nll", "val_top1", "wall_s"]
    if dinfo.is_main and (step == 0 or not log_path.exists()):
        with open(log_path, "w", newline="") as f:
            csv.writer(f).writerow(log_fields)
    elif dinfo.is_main:  # drop log rows past the resumed step (they will be recomputed identically)
        rows = list(csv.DictReader(open(log_path)))
        with open(log_path, "w", newline="") as f:
            w = csv.DictWriter(f, log_fields)
            w.writeheader()
            w.writerows([r for r in rows if int(r["step"]) <= step])

    model.train()
    t0 = time.time()
    cpu_t0 = time.process_time()
    tok_count, tok_t0 = 0, time.time()
    bar = tqdm(total=cfg.max_steps, initial=step, disable=not (progress and dinfo.is_main), desc="pretrain", dynamic_ncols=True)
    while step < cfg.max_steps:
        torch.manual_seed(cfg.seed * 1_000_003 + step)
        lr = lr_at(step, cfg)
        for g in opt.param_groups:
            g["lr"] = lr * g.get("lr_mult", 1.0)
        batch, targets, gen_state = next(inputs)
        gen = torch.Generator()
        gen.set_state(gen_state)
        n_tokens = int(batch.agent_token_valid.sum())  # of the global batch
        if targets is not None:
            targets = ddp.shard_like(targets, batch, dinfo).to(device)
        batch = ddp.shard_batch(batch, dinfo).to(device)  # this rank's scenes (the whole batch in one process)
        with autocast(device, cfg.precision):
            if cfg.fast:
                hidden = None
                if cfg.prev_token_drop_prob > 0:  # drawn from the step's generator: resume stays exact
                    hidden = (torch.rand(batch.agent_token.shape, generator=gen) < cfg.prev_token_drop_prob).to(device)
                loss, acc = packed_loss(model, batch, cfg.label_smoothing, targets, forward=fwd, prev_hidden=hidden)
            else:
                loss, acc = model.loss(batch, fwd(batch), label_smoothing=cfg.label_smoothing, targets=targets)
        n_mine = ddp.count_loss_tokens(batch, N_TOK)
        loss_bwd, loss, acc = ddp.global_token_mean(loss, acc, n_mine, dinfo)  # loss_bwd is loss in one process
        opt.zero_grad(set_to_none=True)
        loss_bwd.backward()
        if cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        opt.step()
        step += 1
        tok_count += n_tokens
        bar.update(1)
        bar.set_postfix(loss=f"{loss.item():.3f}", acc=f"{float(acc):.3f}", lr=f"{lr:.1e}")
        row = None
        if step % cfg.log_every == 0 or step == cfg.max_steps:
            tps = tok_count / max(time.time() - tok_t0, 1e-9)
            tok_count, tok_t0 = 0, time.time()
            row = {"step": step, "lr": lr, "loss": float(loss), "acc": float(acc), "tokens_per_s": tps, "wall_s": time.time() - t0}
        if val_ds is not None and dinfo.is_main and (step % cfg.eval_every == 0 or step == cfg.max_steps):
            ev = evaluate_nll(model, val_ds, collate, cfg.batch_size, cfg.eval_batches, device=device, packed=cfg.fast)
            row = row or {"step": step, "lr": lr, "loss": float(loss), "acc": float(acc), "wall_s": time.time() - t0}
            row.update(val_nll=ev["nll"], val_top1=ev["top1"])
            bar.write(f"[pretrain] step {step}: val nll {ev['nll']:.3f} top1 {ev['top1']:.3f}")
        if row and dinfo.is_main:
            with open(log_path, "a", newline="") as f:
                csv.DictWriter(f, log_fields).writerow(row)
        seen["agent_tokens"] += n_tokens
        seen["cpu_s"] += time.process_time() - cpu_t0
        cpu_t0 = time.process_time()
        if dinfo.is_main and (step % cfg.ckpt_every == 0 or step == cfg.max_steps):
            save_train_state(state_dir, model, opt, {"step": step, "config": asdict(cfg), "seen": dict(seen)})
            write_run_state(out, cfg, step, seen)
        if dinfo.is_main and cfg.keep_every and step % cfg.keep_every == 0:
            save_checkpoint(out / f"ckpt-{step:06d}", model, vocab, extra={"train": _train_info(cfg, step, seen)})
        if stop_at_step is not None and step >= stop_at_step:
            bar.close()
            ddp.barrier(dinfo)
            ddp.shutdown(dinfo)
            return None
    bar.close()
    final = out / "final"
    if dinfo.is_main:
        extra = {"train": {**_train_info(cfg, step, seen), "wall_s": time.time() - t0}}
        if dinfo.enabled:
            extra["train"]["world_size"] = dinfo.world_size
        save_checkpoint(final, model, vocab, extra=extra)
    ddp.barrier(dinfo)
    ddp.shutdown(dinfo)
    return final


def run_from_cli(config_path: str | None, overrides: list[str], resume: bool) -> Path:
    cfg = load_config(PretrainConfig, config_path, overrides)
    return pretrain(cfg, resume=resume, progress=os.environ.get("R1SIM_NO_PROGRESS") is None)
