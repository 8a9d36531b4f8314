"""The fast training path: packed forward == padded forward, reach crop changes no logit, the fast path trains
like the reference path, the compact token dataset rebuilds the tokenized scenes exactly, device selection."""

import csv

import numpy as np
import pytest
import torch

from r1sim_sumo.config import ConfigError
from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.packed import loss_mask, packed_loss, reach_radius_m
from r1sim_sumo.model.policy import TrafficPolicy
from r1sim_sumo.model.synthetic import synthetic_batch, synthetic_vocab
from r1sim_sumo.scenario import write_dataset
from r1sim_sumo.tokens.batch import TokenizedDataset, collate, crop_map_to_reach
from r1sim_sumo.tokens.compact import CompactFormatError, CompactTokenDataset, build_compact
from r1sim_sumo.train.pretrain import PretrainConfig, pretrain, resolve_device


def _model(seed=0, dropout=0.0):
    torch.manual_seed(seed)
    cfg = PolicyConfig.preset("nano", agent_k=8, map_agent_k=8, map_k=8, dropout=dropout, agent_layers=2)
    voc = synthetic_vocab(cfg.vocab_sizes)
    return TrafficPolicy(cfg, voc), voc


def _jittered_batch(voc, seed=2):
    b = synthetic_batch(voc, num_scenes=3, num_agents=20, num_map_tokens=300, seed=seed, vehicle_fraction=0.6)
    g = torch.Generator().manual_seed(seed)  # the synthetic grid map has exact distance ties; real maps do not
    return b._replace(map_pos=b.map_pos + torch.rand(b.map_pos.shape, generator=g) * 0.01)


def test_packed_logits_and_gradients_equal_the_padded_forward():
    model, voc = _model()
    b = _jittered_batch(voc)
    mask = loss_mask(b)
    assert (b.agent_type[b.agent_mask.bool()] > 0).any(), "the batch must exercise the smaller vocabularies"
    ref_logits = model(b)
    ref = ref_logits[mask]
    got = model(b, out_mask=mask)
    assert got.shape == ref.shape
    fin = torch.isfinite(ref)
    assert torch.equal(torch.isfinite(got), fin)  # same -inf pattern (types with a smaller vocabulary)
    assert (got[fin] - ref[fin]).abs().max() < 1e-4
    l_ref, _ = model.loss(b, ref_logits)
    l_ref.backward()
    g_ref = [p.grad.clone() for p in model.parameters()]
    model.zero_grad()
    l_fast, _ = packed_loss(model, b)
    l_fast.backward()
    assert abs(float(l_ref) - float(l_fast)) < 1e-5
    for p, g in zip(model.parameters(), g_ref, strict=True):
        assert torch.allclose(p.grad, g, rtol=1e-3, atol=1e-6)


def test_packed_forward_rejects_rows_without_a_valid_pose():
    model, voc = _model()
    b = _jittered_batch(voc)
    bad = ~b.pose_valid[:, :, :18].bool()
    assert bad.any()
    with pytest.raises(ValueError, match="valid pose"):
        model(b, out_mask=bad)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from r1sim_sumo.data.highway_reference import generate_highway_scenarios
    from r1sim_sumo.tokens.motion_vocab import VocabBuildConfig
    from r1sim_sumo.tokens.vocab_build import build_vocab_from_dataset

    root = tmp_path_factory.mktemp("fast")
    scs = []
    for env in ("merge-v0", "intersection-v0"):
        scs += generate_highway_scenarios(env, seed=0, n_episodes=1, episode_s=12.0, stride_steps=10, progress=False)
    write_dataset(root / "train", scs[:-3], shard_size=4)
    write_dataset(root / "val", scs[-3:], shard_size=4)
    vocab, _ = build_vocab_from_dataset(scs, VocabBuildConfig(size=(64, 16, 16), heldout_fraction=0.0, min_real_segments=10, n_synthetic=500))
    vocab.save(root / "vocab.safetensors")
    build_compact(root, vocab, root / "tokens", workers=1, progress=False)
    return root, vocab



@pytest.mark.highway
def test_reach_crop_changes_no_logit(data):
    root, vocab = data
    ds = TokenizedDataset(root / "train", vocab)
    torch.manual_seed(0)
    cfg = PolicyConfig.preset("nano", vocab_sizes=vocab.sizes, agent_layers=2, dropout=0.0)
    model = TrafficPolicy(cfg, [torch.as_tensor(vocab.traj[t]) for t in range(3)]).eval()
    scenes = [ds[i] for i in range(min(4, len(ds)))]
    cropped = [crop_map_to_reach(s, reach_radius_m(cfg) + 1.0) for s in scenes]
    full, small = collate(scenes), collate(cropped)
    assert small.map_mask.sum() < full.map_mask.sum(), "the crop must drop tokens for this test to mean anything"
    with torch.no_grad():
        mask = loss_mask(full)
        ref = model(full)[mask]
        got = model(small, out_mask=mask)
    d = (got - ref).abs()
    assert d.max() < 1e-3 and d.mean() < 2e-5  # float rounding only (other matmul shapes)


@pytest.mark.highway
def test_compact_dataset_rebuilds_the_tokenized_scenes_exactly(data):
    root, vocab = data
    for split in ("train", "val"):
        comp = CompactTokenDataset(root / "tokens", split)
        ref = TokenizedDataset(root / split, vocab)
        assert len(comp) == len(ref)
        for i in range(len(ref)):
            a, b = comp[i], ref[i]
            for f in a.agents.FIELDS:
                assert np.array_equal(getattr(a.agents, f), getattr(b.agents, f)), (split, i, f)
            for f in a.map.FIELDS:
                assert np.array_equal(getattr(a.map, f), getattr(b.map, f)), (split, i, f)
            x = comp.noised(i, 3, np.random.default_rng([1, i]))
            y = ref.noised(i, 3, np.random.default_rng([1, i]))
            for f in (*x.agents.FIELDS, "target"):
                assert np.array_equal(getattr(x.agents, f), getattr(y.agents, f)), (split, i, f)


def test_compact_dataset_errors_name_the_file(tmp_path):
    with pytest.raises(CompactFormatError, match="manifest.json.*r1sim tokens build"):
        CompactTokenDataset(tmp_path, "train")


def _cfg(root, out, **kw):
    base = dict(train_data=str(root / "train"), val_data=str(root / "val"), vocab=str(root / "vocab.safetensors"),
                batch_size=2, max_steps=20, warmup_steps=1, lr=3e-3, eval_every=100, ckpt_every=100, log_every=1,
                out_dir=str(out), threads=1, model_overrides={"agent_layers": 2, "map_layers": 1, "dropout": 0.0})
    base.update(kw)
    return PretrainConfig(**base)


def _losses(out):
    return [float(r["loss"]) for r in csv.DictReader(open(out / "log.csv"))]


@pytest.mark.highway
def test_fast_path_trains_like_the_reference_path(data, tmp_path):
    root, _ = data
    pretrain(_cfg(root, tmp_path / "ref", fast=False, precision="fp32"), progress=False)
    pretrain(_cfg(root, tmp_path / "fast32", fast=True, precision="fp32"), progress=False)
    pretrain(_cfg(root, tmp_path / "fast16", fast=True, precision="bf16"), progress=False)
    ref, f32, f16 = (np.array(_losses(tmp_path / n)) for n in ("ref", "fast32", "fast16"))
    assert len(ref) == len(f32) == len(f16) == 20
    assert ref[-1] < ref[0] - 0.5  # it learns
    # same computation; float rounding, and highway-env's straight lanes put map tokens at exactly equal distances,
    # where the neighbour search of a packed and a padded batch may pick different (equally near) tokens
    assert np.abs(f32 - ref).max() < 5e-3
    assert np.abs(f16 - ref).max() < 0.05  # bf16 forward: within bf16 tolerance over 20 steps
    assert abs(f16[-5:].mean() - ref[-5:].mean()) < 0.02


@pytest.mark.highway
def test_pretrain_on_the_compact_dataset_reproduces_the_scenario_path(data, tmp_path):
    root, _ = data
    for noise in (1, 3):
        a, b = tmp_path / f"scn{noise}", tmp_path / f"tok{noise}"
        pretrain(_cfg(root, a, precision="fp32", token_noise_top_k=noise), progress=False)
        pretrain(_cfg(root, b, precision="fp32", token_noise_top_k=noise, tokens=str(root / "tokens"),
                      train_data="unused", val_data=None, vocab=None), progress=False)
        assert _losses(a) == _losses(b)  # exactly: the same scenes, tokens and poses


@pytest.mark.highway
def test_batches_built_ahead_by_loader_workers_train_exactly_like_in_process(data, tmp_path):
    root, _ = data
    kw = dict(precision="fp32", token_noise_top_k=3, tokens=str(root / "tokens"), train_data="unused", val_data=None,
              vocab=None, max_steps=8, history_drop_prob=0.3, prev_token_drop_prob=0.2, steady_history_prob=0.5)
    pretrain(_cfg(root, tmp_path / "w0", loader_workers=0, **kw), progress=False)
    pretrain(_cfg(root, tmp_path / "w2", loader_workers=2, **kw), progress=False)
    assert len(_losses(tmp_path / "w0")) == 8
    assert _losses(tmp_path / "w0") == _losses(tmp_path / "w2")  # the same batches, masks and labels
    with pytest.raises(ConfigError, match="loader_workers"):
        PretrainConfig(loader_workers=-1)
    with pytest.raises(ConfigError, match="steady_history_prob"):
        PretrainConfig(steady_history_prob=1.5)


def test_device_selection():
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu").type == "cpu"
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="key 'device'"):
            resolve_device("cuda")
    with pytest.raises(ConfigError, match="device"):
        PretrainConfig(device="gpu")
    with pytest.raises(ConfigError, match="precision"):
        PretrainConfig(precision="fp16")


def test_hidden_previous_tokens_act_as_unknown_tokens():
    model, voc = _model()
    model.eval()
    b = _jittered_batch(voc)
    mask = loss_mask(b)
    with torch.no_grad():
        plain = model(b, out_mask=mask)
        assert torch.equal(model(b, out_mask=mask, prev_hidden=torch.zeros_like(mask)), plain)
        hidden_all = model(b, out_mask=mask, prev_hidden=torch.ones_like(mask))
        unknown = model(b._replace(agent_token_valid=torch.zeros_like(b.agent_token_valid)), out_mask=mask)
    fin = torch.isfinite(plain)
    assert torch.allclose(hidden_all[fin], unknown[fin], atol=1e-5)
    assert (hidden_all[fin] - plain[fin]).abs().max() > 1e-2  # the input matters


def test_attention_einsum_path_equals_the_bmm_path(monkeypatch):
    from r1sim_sumo.model import layers

    torch.manual_seed(0)
    blk = layers.RelAttentionBlock(64, 4, 128, 4, 0.0)
    x, e = torch.randn(3000, 64), torch.randn(3000, 8, 128)
    mask = torch.rand(3000, 8) > 0.3
    mask[0] = False  # a query without neighbours
    out_einsum = blk(x, blk.normed(x), e, mask)
    monkeypatch.setattr(layers, "EINSUM_MIN_ROWS", 10**9)
    out_bmm = blk(x, blk.normed(x), e, mask)
    assert (out_einsum - out_bmm).abs().max() < 1e-4


def test_tree_neighbour_search_selects_the_brute_force_neighbours():
    """The k-d tree search of the packed path picks the same neighbour sets as the brute-force search (no exact
    distance ties with random positions), including scenes with fewer keys than k and keys beyond the radius."""
    from r1sim_sumo.model.packed import _knn_per_scene, _knn_per_scene_dense

    g = torch.Generator().manual_seed(3)
    counts_q, counts_k = torch.tensor([40, 0, 25, 7]), torch.tensor([300, 5, 3, 60])
    q_off = torch.nn.functional.pad(counts_q.cumsum(0), (1, 0))
    k_off = torch.nn.functional.pad(counts_k.cumsum(0), (1, 0))
    q = torch.rand(int(counts_q.sum()), 2, generator=g) * 120.0
    k = torch.rand(int(counts_k.sum()), 2, generator=g) * 120.0
    i_t, ok_t = _knn_per_scene(q, q_off, k, k_off, 8, 15.0)
    i_d, ok_d = _knn_per_scene_dense(q, q_off, k, k_off, 8, 15.0)
    assert ok_t.sum() == ok_d.sum() and 0 < int(ok_t.sum()) < ok_t.numel()  # some neighbours are out of reach
    for row in range(q.shape[0]):
        assert set(i_t[row][ok_t[row]].tolist()) == set(i_d[row][ok_d[row]].tolist())


@pytest.mark.highway
def test_joined_datasets_read_the_parts_in_order_and_refuse_another_vocabulary(data, tmp_path):
    from r1sim_sumo.tokens.compact import JoinedTokenDatasets
    from r1sim_sumo.tokens.motion_vocab import VocabBuildConfig
    from r1sim_sumo.tokens.vocab_build import build_vocab_from_dataset

    root, _ = data
    a, b = CompactTokenDataset(root / "tokens", "train"), CompactTokenDataset(root / "tokens", "val")
    joined = JoinedTokenDatasets([a, b])
    assert len(joined) == len(a) + len(b)
    for i, (part, j) in enumerate([(a, k) for k in range(len(a))] + [(b, k) for k in range(len(b))]):
        x, y = joined[i], part[j]
        assert np.array_equal(x.agents.token, y.agents.token) and x.scenario_id == y.scenario_id
        n1, n2 = joined.noised(i, 3, np.random.default_rng([2, i])), part.noised(j, 3, np.random.default_rng([2, i]))
        assert np.array_equal(n1.agents.target, n2.agents.target)
    assert joined[-1].scenario_id == b[len(b) - 1].scenario_id
    with pytest.raises(IndexError):
        joined[len(joined)]
    # a part tokenized with another vocabulary is refused, naming it and the fix
    from r1sim_sumo.scenario import ScenarioDataset
    other, _ = build_vocab_from_dataset(list(ScenarioDataset(root / "train")), VocabBuildConfig(
        size=(32, 16, 16), heldout_fraction=0.0, min_real_segments=10, n_synthetic=300))
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "train").symlink_to(root / "train")
    (tmp_path / "o" / "val").symlink_to(root / "val")
    build_compact(tmp_path / "o", other, tmp_path / "o_tok", workers=1, progress=False)
    with pytest.raises(CompactFormatError, match="another vocabulary.*--vocab"):
        JoinedTokenDatasets([a, CompactTokenDataset(tmp_path / "o_tok", "train")])


@pytest.mark.highway
def test_pretrain_with_extra_tokens_samples_the_joined_train_splits(data, tmp_path):
    import json
    import shutil

    root, _ = data
    extra = shutil.copytree(root / "tokens", tmp_path / "tokens_copy")  # another folder, the same vocabulary
    cfg = _cfg(root, tmp_path / "x", precision="fp32", tokens=str(root / "tokens"), extra_tokens=[str(extra)],
               train_data="unused", val_data=None, vocab=None, max_steps=3)
    pretrain(cfg, progress=False)
    assert len(_losses(tmp_path / "x")) == 3
    needs = json.loads((tmp_path / "x" / "run_state.json").read_text())["needs"]
    assert str(root / "tokens") in needs and str(extra) in needs, needs  # a resume needs every dataset the run joins
    with pytest.raises(ValueError, match="extra_tokens.*needs 'tokens'"):
        pretrain(_cfg(root, tmp_path / "y", extra_tokens=[str(root / "tokens")]), progress=False)


def test_edge_attention_backward_equals_autograd():
    """The hand-written backward of the training attention core gives autograd's gradients of the plain version,
    including queries without any neighbour (zero output, zero gradient) and masked edges."""
    from r1sim_sumo.model.layers import EdgeAttention, edge_attention

    g = torch.Generator().manual_seed(1)
    qe = torch.randn(500, 4, 32, generator=g, dtype=torch.float64, requires_grad=True)
    e = torch.randn(500, 7, 32, generator=g, dtype=torch.float64, requires_grad=True)
    mask = torch.rand(500, 1, 7, generator=g) > 0.3
    mask[:5] = False  # queries without neighbours
    up = torch.randn(500, 4, 32, generator=g, dtype=torch.float64)
    plain = edge_attention(qe, e, mask, big=True)
    fused = EdgeAttention.apply(qe, e, mask)
    assert torch.allclose(plain, fused, atol=1e-12) and bool((fused[:5] == 0).all())
    g_plain = torch.autograd.grad((plain * up).sum(), (qe, e))
    g_fused = torch.autograd.grad((fused * up).sum(), (qe, e))
    for a, b in zip(g_plain, g_fused, strict=True):
        assert torch.allclose(a, b, atol=1e-10)
    assert bool((g_fused[0][:5] == 0).all()) and float(g_fused[1][mask.squeeze(1).logical_not()].abs().max()) == 0.0


def test_edge_attention_under_bf16_autocast_matches_the_plain_version():
    from r1sim_sumo.model.layers import EdgeAttention, edge_attention

    torch.manual_seed(2)
    qe = torch.randn(300, 4, 16, requires_grad=True)
    e = torch.randn(300, 6, 16, requires_grad=True)
    mask = torch.rand(300, 1, 6) > 0.2
    with torch.autocast("cpu", dtype=torch.bfloat16):
        plain = edge_attention(qe, e, mask, big=True)
        fused = EdgeAttention.apply(qe, e, mask)
    assert fused.dtype == plain.dtype == torch.bfloat16
    assert torch.allclose(plain.float(), fused.float(), atol=2e-2)
    gq, ge = torch.autograd.grad(fused.float().sum(), (qe, e))
    assert gq.dtype == ge.dtype == torch.float32 and bool(torch.isfinite(gq).all() & torch.isfinite(ge).all())


def test_smoothed_cross_entropy_equals_the_log_softmax_form():
    """The fused loss and its gradient equal label smoothing over each row's own vocabulary written with
    log_softmax, for rows of a full and of a smaller vocabulary (logits -inf outside it)."""
    from r1sim_sumo.model.packed import SmoothedCrossEntropy

    g = torch.Generator().manual_seed(0)
    n, V, eps = 400, 64, 0.1
    vocab = torch.where(torch.rand(n, generator=g) < 0.3, 16, 64)
    outside = torch.arange(V)[None] >= vocab[:, None]
    z = torch.randn(n, V, generator=g, dtype=torch.float64).masked_fill(outside, float("-inf")).requires_grad_()
    target = (torch.rand(n, generator=g) * vocab).long()
    fused = SmoothedCrossEntropy.apply(z, target, vocab, eps)
    logp = torch.log_softmax(z, -1)
    ref = ((1 - eps) * -logp.gather(-1, target[:, None]).squeeze(-1) - eps * logp.masked_fill(outside, 0).sum(-1) / vocab).mean()
    assert abs(float(fused) - float(ref)) < 1e-5  # the fused forward runs in fp32
    g_fused, = torch.autograd.grad(fused, z)
    g_ref, = torch.autograd.grad(ref, z)
    assert torch.allclose(g_fused, g_ref, atol=1e-7) and float(g_fused[outside].abs().max()) == 0.0
    one = SmoothedCrossEntropy.apply(z[vocab == 64], target[vocab == 64], vocab[vocab == 64], eps)  # one vocabulary
    assert bool(torch.isfinite(one))


@pytest.mark.highway
def test_compact_dataset_keeps_each_maps_geometry(data, tmp_path):
    """``<split>.polylines.npz``: every scene's map geometry (lanes, road edges, ids, widths, limits) exactly as the
    scenario's, without signal states; a folder built without it is refused with the file and the fix named."""
    import shutil

    from r1sim_sumo.scenario import ScenarioDataset
    from r1sim_sumo.tokens.compact import POLYLINE_FIELDS

    root, _ = data
    comp, scn = CompactTokenDataset(root / "tokens", "train"), ScenarioDataset(root / "train")
    kinds = set()
    for i in range(len(scn)):
        want, got = scn[i].map, comp.polylines(i)
        for f in POLYLINE_FIELDS:
            assert np.array_equal(np.asarray(getattr(want, f)), np.asarray(getattr(got, f))), (i, f)
        assert got.tl_state.shape == (got.num_polylines, 0)
        assert got.content_key() == want.content_key()
        kinds.add(got.content_key())
    assert len(kinds) == len(comp._polylines) == comp.a["map_n_tokens"].size  # one geometry per de-duplicated map
    old = tmp_path / "old"
    shutil.copytree(root / "tokens", old)
    (old / "train.polylines.npz").unlink()
    with pytest.raises(CompactFormatError, match="train.polylines.npz.*r1sim tokens build"):
        CompactTokenDataset(old, "train").polylines(0)


@pytest.mark.highway
def test_grpo_on_the_compact_dataset_runs_the_scenario_path_exactly(data, tmp_path):
    """``train_tokens`` (what travels to a GPU machine): GRPO on a compact dataset draws the same scenes, scores them
    with the same rewards (the offroad part from the kept map geometry) and makes the same updates as on the scenario
    dataset it was built from; a compact dataset of another vocabulary is refused."""
    from r1sim_sumo import load_policy
    from r1sim_sumo.tokens.motion_vocab import MotionVocab
    from r1sim_sumo.train.grpo import GRPOConfig, compact_source, finetune
    from r1sim_sumo.train.rewards import RewardConfig

    root, vocab = data
    start = pretrain(_cfg(root, tmp_path / "pre", max_steps=3, precision="fp32"), progress=False)
    kw = dict(init_checkpoint=str(start), num_rollouts=4, batch_scenes=2, max_iters=3, ppo_epochs=1, num_minibatches=2,
              sampler="topk:5", lr=1e-3, reward=RewardConfig(offroad=True), threads=1)
    a = finetune(GRPOConfig(train_data=str(root / "train"), out_dir=str(tmp_path / "scn"), **kw), progress=False)
    b = finetune(GRPOConfig(train_tokens=[str(root / "tokens")], out_dir=str(tmp_path / "tok"), **kw), progress=False)
    keys = ("reward", "collision_rate", "offroad_rate", "distance_m", "loss", "kl")

    def rows(run):
        return [{k: r[k] for k in keys} for r in csv.DictReader(open(tmp_path / run / "log.csv"))]

    assert len(rows("scn")) == 3 and rows("scn") == rows("tok")
    assert any(float(r["offroad_rate"]) > 0 or float(r["reward"]) < 1 for r in rows("scn"))  # scored, not vacuous
    wa, wb = load_policy(a).model.state_dict(), load_policy(b).model.state_dict()
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    assert not all(torch.equal(wa[k], load_policy(start).model.state_dict()[k]) for k in wa)  # it did update
    with pytest.raises(ValueError, match="train_tokens.*not the policy's vocabulary"):
        compact_source([str(root / "tokens")], MotionVocab.from_traj({t: v[::-1] for t, v in vocab.traj.items()}))


def test_grpo_config_refuses_what_the_gpu_path_does_not_take():
    from r1sim_sumo.train.grpo import GRPOConfig

    with pytest.raises(ValueError, match="device 'tpu' unknown"):
        GRPOConfig(device="tpu")
    for bad in (dict(method="sft"), dict(rollout_source="sumo"), dict(steady_start_prob=0.5)):
        with pytest.raises(ValueError, match="device 'cuda' takes method grpo"):
            GRPOConfig(device="cuda", **bad)
    with pytest.raises(ValueError, match="train_tokens replaces"):
        GRPOConfig(train_tokens=["data/tokens/x"], extra_train_data=["data/generated/rings/train"])
    GRPOConfig(device="cuda", train_tokens=["data/tokens/x"])  # the GPU run's combination is accepted
