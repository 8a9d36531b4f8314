"""Tests of the policy model (r1sim_sumo.model): presets, shapes, causality, KV cache, training, checkpoints."""

from __future__ import annotations

import json
import math
import shutil

import pytest
import torch

import r1sim_sumo
from r1sim_sumo.config import ConfigError
from r1sim_sumo.model import (
    CheckpointError,
    PolicyConfig,
    TrafficPolicy,
    load_checkpoint,
    load_policy,
    save_checkpoint,
)
from r1sim_sumo.model.layers import knn, pack_pose, rel_pose_features
from r1sim_sumo.model.policy import token_nll_and_correct
from r1sim_sumo.model.synthetic import synthetic_batch, synthetic_vocab
from r1sim_sumo.tokens import MotionVocab

torch.set_num_threads(1)
SIZES = (64, 16, 16)


@pytest.fixture(scope="module")
def vocab() -> MotionVocab:
    return MotionVocab.from_traj({t: v.numpy() for t, v in enumerate(synthetic_vocab(SIZES, seed=1))})


def make_model(vocab, seed: int = 0, **kw) -> TrafficPolicy:
    torch.manual_seed(seed)
    cfg = PolicyConfig.preset("nano", vocab_sizes=vocab.sizes, **kw)
    return TrafficPolicy(cfg, [torch.from_numpy(vocab.traj[t]) for t in range(3)])


def make_batch(vocab, **kw):
    kw = {"num_scenes": 2, "num_agents": 10, "num_map_tokens": 120, "extent_m": 100.0, "seed": 3, "vehicle_fraction": 0.6, **kw}
    return synthetic_batch([torch.from_numpy(vocab.traj[t]) for t in range(3)], **kw)


# ----------------------------------------------------------------------------- config and layers


@pytest.mark.parametrize("name,lo,hi", [("nano", 0.7e6, 1.5e6), ("tiny", 5e6, 9e6)])
def test_preset_parameter_counts(name, lo, hi):
    cfg = PolicyConfig.preset(name)
    model = TrafficPolicy(cfg, synthetic_vocab(cfg.vocab_sizes))
    assert lo <= model.num_parameters() <= hi


def test_config_refuses_unknown_and_bad_values():
    with pytest.raises(ConfigError, match="hiden_dim"):
        PolicyConfig.from_dict({"hiden_dim": 32})
    with pytest.raises(ConfigError, match="divisible"):
        PolicyConfig(hidden_dim=30, num_heads=4)
    with pytest.raises(ConfigError, match="preset"):
        PolicyConfig.preset("huge")
    assert PolicyConfig.from_dict(PolicyConfig.preset("tiny").to_dict()) == PolicyConfig.preset("tiny")


def test_rel_pose_and_knn():
    dst = pack_pose(torch.tensor([1.0, 2.0]), torch.tensor(math.pi / 2))  # heading north
    src = pack_pose(torch.tensor([[1.0, 12.0], [-4.0, 2.0]]), torch.tensor([math.pi / 2, math.pi]))
    rel = rel_pose_features(src, dst)  # [2, 5]
    torch.testing.assert_close(rel[0], torch.tensor([1.0, 1.0, 0.0, 1.0, 0.0]), atol=1e-6, rtol=0)  # 10 m ahead
    torch.testing.assert_close(rel[1], torch.tensor([0.5, 0.0, 1.0, 0.0, 1.0]), atol=1e-6, rtol=0)  # 5 m left, turned left
    keys = torch.tensor([[[0.0, 0.0], [3.0, 0.0], [1.0, 0.0], [50.0, 0.0]]])
    idx, ok = knn(keys, keys, torch.tensor([[True, True, False, True]]), k=2, radius_m=10.0, exclude_self=True)
    found = dict(zip(idx[0, 0].tolist(), ok[0, 0].tolist(), strict=True))  # neighbours of key 0
    assert found == {1: True, 3: False}  # key 2 invalid, key 0 itself excluded, key 3 beyond 10 m
    assert not ok[0, 3].any()  # 47 m and 50 m away


# ----------------------------------------------------------------------------- forward


def test_forward_shapes_and_type_masking(vocab):
    model = make_model(vocab).eval()
    batch = make_batch(vocab)
    with torch.no_grad():
        logits = model(batch)
    B, A = batch.agent_mask.shape
    assert logits.shape == (B, A, 18, max(SIZES))
    assert torch.isfinite(logits).any()
    for t, v in enumerate(SIZES):
        sel = batch.agent_type == t
        if sel.any():
            lg = logits[sel]  # [n, 18, V]
            assert torch.isfinite(lg[..., :v]).all()
            assert torch.isneginf(lg[..., v:]).all()


def test_forward_refuses_out_of_vocabulary_tokens(vocab):
    model = make_model(vocab)
    batch = make_batch(vocab)
    tok = batch.agent_token.clone()
    b, a = torch.nonzero((batch.agent_type == 1) & batch.agent_mask)[0].tolist()
    tok[b, a, 5] = SIZES[1]  # one past the cyclist vocabulary
    with pytest.raises(ValueError, match="outside the vocabulary"):
        model(batch._replace(agent_token=tok, agent_token_valid=batch.agent_token_valid | (tok >= 0)))


def test_causal_future_does_not_change_past_logits(vocab):
    model = make_model(vocab).eval()
    batch = make_batch(vocab)
    k0 = 7
    g = torch.Generator().manual_seed(5)
    tok = batch.agent_token.clone()
    tok[:, :, k0:] = torch.where(tok[:, :, k0:] >= 0, torch.randint(0, 16, tok[:, :, k0:].shape, generator=g), -1)
    xy = batch.pose_xy.clone()
    xy[:, :, k0 + 1 :] += torch.randn(xy[:, :, k0 + 1 :].shape, generator=g) * 3.0
    changed = batch._replace(agent_token=tok, pose_xy=xy)
    with torch.no_grad():
        a, b = model(batch), model(changed)
    valid = (batch.pose_valid[:, :, :18] & batch.agent_mask[..., None]).unsqueeze(-1) & torch.isfinite(a)
    torch.testing.assert_close(a[:, :, : k0 + 1][valid[:, :, : k0 + 1]], b[:, :, : k0 + 1][valid[:, :, : k0 + 1]], atol=1e-6, rtol=0)
    assert (a[:, :, k0 + 1 :][valid[:, :, k0 + 1 :]] - b[:, :, k0 + 1 :][valid[:, :, k0 + 1 :]]).abs().max() > 1e-3


# ----------------------------------------------------------------------------- KV cache


@pytest.mark.parametrize("grad", [False, True])
def test_cached_step_equals_full_forward(vocab, grad):
    model = make_model(vocab).eval()
    batch = make_batch(vocab)
    G = 3
    rep = lambda t: t.repeat(G, *([1] * (t.dim() - 1)))  # noqa: E731
    tok = torch.where(batch.agent_token_valid, batch.agent_token, -1)
    with torch.set_grad_enabled(grad):
        full = model(batch)
        cache = model.init_rollout(batch, num_rollouts=G)
        worst = 0.0
        for k in range(2, 18):
            out = model.step(cache, k, rep(tok[:, :, k - 1]), rep(batch.pose_xy[:, :, k]), rep(batch.pose_yaw[:, :, k]), rep(batch.pose_valid[:, :, k]))
            ref = rep(full[:, :, k])
            sel = rep(batch.pose_valid[:, :, k] & batch.agent_mask).unsqueeze(-1) & torch.isfinite(ref)
            assert torch.equal(torch.isfinite(out), torch.isfinite(ref))
            worst = max(worst, float((out - ref).detach()[sel].abs().max()))
    assert worst < 1e-5
    with pytest.raises(ValueError, match="expected step_k"):
        model.step(cache, 5, rep(tok[:, :, 4]), rep(batch.pose_xy[:, :, 5]), rep(batch.pose_yaw[:, :, 5]), rep(batch.pose_valid[:, :, 5]))


def test_short_cache_gives_the_same_logits_and_refuses_later_steps(vocab):
    """A cache sized for steps up to ``last_step`` (one drop-in decision) computes exactly what the full cache does."""
    model = make_model(vocab).eval()
    batch = make_batch(vocab)
    tok = torch.where(batch.agent_token_valid, batch.agent_token, -1)
    last = 5
    with torch.no_grad():
        full = model.init_rollout(batch)
        short = model.init_rollout(batch, last_step=last)
        assert short.t_xn.shape[3] < full.t_xn.shape[3]
        for k in range(2, last + 1):
            args = (tok[:, :, k - 1], batch.pose_xy[:, :, k], batch.pose_yaw[:, :, k], batch.pose_valid[:, :, k])
            assert torch.equal(model.step(full, k, *args), model.step(short, k, *args))
        with pytest.raises(ValueError, match="step_k must be in"):
            model.step(short, last + 1, tok[:, :, last], batch.pose_xy[:, :, last + 1], batch.pose_yaw[:, :, last + 1],
                       batch.pose_valid[:, :, last + 1])
    with pytest.raises(ValueError, match="last_step"):
        model.init_rollout(batch, upto_step=4, last_step=1)


def test_rollouts_are_independent(vocab):
    """Changing rollout 1's poses must not change rollout 0's logits (no leakage across S rows)."""
    model = make_model(vocab).eval()
    batch = make_batch(vocab, num_scenes=1)
    tok = torch.where(batch.agent_token_valid, batch.agent_token, -1)
    with torch.no_grad():
        cache = model.init_rollout(batch, num_rollouts=2)
        xy = batch.pose_xy[:, :, 2].repeat(2, 1, 1)
        xy[1] += 5.0
        out = model.step(cache, 2, tok[:, :, 1].repeat(2, 1), xy, batch.pose_yaw[:, :, 2].repeat(2, 1), batch.pose_valid[:, :, 2].repeat(2, 1))
        ref = model(batch)[:, :, 2]
    sel = (batch.pose_valid[0, :, 2] & batch.agent_mask[0]).unsqueeze(-1) & torch.isfinite(ref[0])
    assert float((out[0] - ref[0])[sel].abs().max()) < 1e-5


# ----------------------------------------------------------------------------- training


def test_loss_decreases_on_overfit_batch(vocab):
    model = make_model(vocab, dropout=0.0, agent_layers=2, map_layers=1).train()
    batch = make_batch(vocab, num_scenes=1, num_agents=5, num_map_tokens=30, extent_m=40.0)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        loss, acc = model.loss(batch, model(batch), label_smoothing=0.0)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert math.isfinite(losses[-1]) and losses[-1] < 0.5 * losses[0], losses[::8]
    assert float(acc) > 0.5


def test_loss_masks(vocab):
    model = make_model(vocab).eval()
    batch = make_batch(vocab)
    with torch.no_grad():
        logits = model(batch)
        full, _ = model.loss(batch, logits)
        fut, _ = model.loss(batch, logits, include_history=False)
        hist_garbage = logits.clone()
        hist_garbage[:, :, :2] = torch.randn_like(hist_garbage[:, :, :2]) * 100
        fut2, _ = model.loss(batch, hist_garbage, include_history=False)
        plain, _ = model.loss(batch, logits, label_smoothing=0.0)
        nll, correct, n = token_nll_and_correct(batch, logits, future_only=False)
        nll_f, _, n_f = token_nll_and_correct(batch, logits)
    assert torch.isfinite(full) and full != fut
    torch.testing.assert_close(fut, fut2)
    assert nll / n == pytest.approx(float(plain), rel=1e-5)
    assert 0 <= correct <= n == int((batch.agent_token_valid & batch.agent_mask[..., None]).sum())
    plain_f, _ = model.loss(batch, logits, label_smoothing=0.0, include_history=False)
    assert n_f == int((batch.agent_token_valid & batch.agent_mask[..., None])[:, :, 2:].sum()) < n
    assert nll_f / n_f == pytest.approx(float(plain_f), rel=1e-5)


# ----------------------------------------------------------------------------- checkpoints


@pytest.fixture()
def saved(tmp_path, vocab):
    model = make_model(vocab, seed=4).eval()
    d = save_checkpoint(tmp_path / "ckpt", model, vocab, extra={"steps": 3})
    return model, d


def _edit_json(d, **changes):
    p = d / "checkpoint.json"
    meta = json.loads(p.read_text())
    for k, v in changes.items():
        if v is None:
            meta.pop(k, None)
        else:
            meta[k] = v
    p.write_text(json.dumps(meta))


def _record_weights(d):
    """Make checkpoint.json's size/hash match the current weights file (to reach the deeper checks)."""
    import hashlib

    w = d / "model.safetensors"
    _edit_json(d, weights={"file": w.name, "bytes": w.stat().st_size, "sha256": hashlib.sha256(w.read_bytes()).hexdigest()})


def test_checkpoint_round_trip(saved, vocab):
    model, d = saved
    pol = load_checkpoint(d, expected_vocab_fingerprint=vocab.fingerprint())
    assert pol.vocab.fingerprint() == vocab.fingerprint() and pol.config == model.config
    assert pol.info["package_version"] == r1sim_sumo.__version__ and pol.info["training"] == {"steps": 3}
    batch = make_batch(vocab)
    with torch.no_grad():
        torch.testing.assert_close(pol.model(batch), model(batch), atol=0, rtol=0)
    assert load_policy(str(d)).vocab.sizes == vocab.sizes


def test_checkpoint_refuses_other_vocabulary(saved, vocab):
    _, d = saved
    with pytest.raises(CheckpointError, match="was requested"):
        load_checkpoint(d, expected_vocab_fingerprint="0123456789abcdef")
    _edit_json(d, vocab_fingerprint="0123456789abcdef")
    with pytest.raises(CheckpointError, match="do not belong together"):
        load_checkpoint(d)
    _edit_json(d, vocab_fingerprint=None)
    with pytest.raises(CheckpointError, match="vocab_fingerprint' missing"):
        load_checkpoint(d)


def test_checkpoint_refuses_other_version(saved):
    _, d = saved
    major, minor = r1sim_sumo.__version__.split(".")[:2]
    _edit_json(d, package_version=f"{major}.{int(minor) + 1}.0")
    with pytest.raises(CheckpointError, match="major.minor"):
        load_checkpoint(d)


def test_checkpoint_refuses_shape_mismatch(saved):
    _, d = saved
    meta = json.loads((d / "checkpoint.json").read_text())
    _edit_json(d, model_config={**meta["model_config"], "hidden_dim": 32})
    with pytest.raises(CheckpointError, match="do not fit model_config"):
        load_checkpoint(d)
    _edit_json(d, model_config={**meta["model_config"], "hidden_size": 32})
    with pytest.raises(CheckpointError, match="hidden_size"):
        load_checkpoint(d)


def test_checkpoint_refuses_pickle(saved):
    model, d = saved
    w = d / "model.safetensors"
    torch.save(model.state_dict(), w)  # a pickle named .safetensors
    with pytest.raises(CheckpointError, match="truncated or replaced"):
        load_checkpoint(d)
    _record_weights(d)
    with pytest.raises(CheckpointError, match="not a readable safetensors"):
        load_checkpoint(d)


def test_checkpoint_refuses_truncated_and_missing(saved, tmp_path):
    _, d = saved
    w = d / "model.safetensors"
    data = w.read_bytes()
    w.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="truncated"):
        load_checkpoint(d)
    _record_weights(d)
    with pytest.raises(CheckpointError, match="not a readable safetensors"):
        load_checkpoint(d)
    w.unlink()
    with pytest.raises(CheckpointError, match="missing"):
        load_checkpoint(d)
    shutil.rmtree(d)
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(d)
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="checkpoint.json"):
        load_checkpoint(tmp_path / "empty")


def test_load_policy_unknown_name():
    with pytest.raises(FileNotFoundError, match="no bundled checkpoint"):
        load_policy("no-such-checkpoint")


def test_small_steps_run_single_threaded_and_restore_the_thread_count(vocab):
    model = make_model(vocab).eval()
    batch = make_batch(vocab)
    tok = torch.where(batch.agent_token_valid, batch.agent_token, -1)
    seen = []
    orig = model._step

    def spy(*a, **k):
        seen.append(torch.get_num_threads())
        return orig(*a, **k)

    model._step = spy
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with torch.no_grad():
            cache = model.init_rollout(batch, num_rollouts=1)
            model.step(cache, 2, tok[:, :, 1], batch.pose_xy[:, :, 2], batch.pose_yaw[:, :, 2], batch.pose_valid[:, :, 2])
        assert set(seen) == {1} and torch.get_num_threads() == 2  # one thread inside, restored after
    finally:
        torch.set_num_threads(before)


def test_token_table_is_cached_in_inference_and_follows_weight_updates(vocab):
    model = make_model(vocab).eval()
    with torch.no_grad():
        a, b = model.token_table(), model.token_table()
        assert a is b  # computed once
        model.token_emb.weight.add_(1.0)  # an optimizer step / load_state_dict changes weights in place
        c = model.token_table()
        assert c is not a and torch.allclose(c, a + 1.0, atol=1e-5)
    model.train()
    t = model.token_table()
    assert t.requires_grad  # training never uses the cache


def test_knn_kdtree_path_selects_the_same_neighbours_as_the_distance_matrix(monkeypatch):
    """Large CPU searches go through a k-d tree (:func:`knn_kdtree`): the same neighbour sets and validity as the
    brute-force distance matrix, with invalid keys, a radius that leaves some queries short of k neighbours, and
    ``exclude_self`` (agents among agents)."""
    from r1sim_sumo.model import layers

    g = torch.Generator().manual_seed(0)
    S, Q, K, k, radius = 3, 300, 900, 16, 20.0
    q = 1000.0 + torch.rand(S, Q, 2, generator=g) * 300.0
    keys = 1000.0 + torch.rand(S, K, 2, generator=g) * 300.0
    kv = torch.rand(S, K, generator=g) > 0.2
    cases = [(q, keys, kv, False), (keys, keys, kv, True)]
    for qq, kk_xy, valid, excl in cases:
        monkeypatch.setattr(layers, "KD_MIN_PAIRS", 1 << 40)  # the distance matrix
        bi, bv = layers.knn(qq, kk_xy, valid, k, radius, exclude_self=excl)
        monkeypatch.setattr(layers, "KD_MIN_PAIRS", 0)  # the k-d tree
        ti, tv = layers.knn(qq, kk_xy, valid, k, radius, exclude_self=excl)
        # brute force, spelled out
        d2 = ((qq.unsqueeze(2) - kk_xy.unsqueeze(1)) ** 2).sum(-1).masked_fill(~valid.unsqueeze(1), float("inf"))
        if excl:
            d2[:, torch.arange(K), torch.arange(K)] = float("inf")
        d, i = torch.topk(d2, k, -1, largest=False)
        want_ok = d <= radius * radius
        assert torch.equal(tv.sum(-1), want_ok.sum(-1)) and torch.equal(bv.sum(-1), want_ok.sum(-1))
        assert 0 < int(want_ok.sum(-1).min()) < k  # some queries have fewer than k neighbours in the radius
        for got_i, got_v in ((ti, tv), (bi, bv)):
            for s in range(S):
                for r in range(0, qq.shape[1], 37):
                    assert set(got_i[s, r][got_v[s, r]].tolist()) == set(i[s, r][want_ok[s, r]].tolist())
        if excl:
            assert not (ti[tv] == torch.arange(K).view(1, K, 1).expand_as(ti)[tv]).any()


def test_inference_decode_through_the_kernel_equals_the_dense_decode(vocab, monkeypatch):
    """Without autograd on a CPU the agent layers hand their dense edges to the C kernel by parts
    (``_decode_dense_gathered``): the same logits as building the edge features (forward and cached steps)."""
    from r1sim_sumo.model import gathered_attention

    if not gathered_attention.available():
        pytest.skip(f"C kernel unavailable: {gathered_attention.unavailable_reason()}")
    model = make_model(vocab).eval()
    batch = make_batch(vocab)
    tok = torch.where(batch.agent_token_valid, batch.agent_token, -1)

    def run():
        with torch.no_grad():
            full = model(batch)
            cache = model.init_rollout(batch)
            steps = [model.step(cache, k, tok[:, :, k - 1], batch.pose_xy[:, :, k], batch.pose_yaw[:, :, k],
                                batch.pose_valid[:, :, k]) for k in range(2, 8)]
        return full, torch.stack(steps, 2)

    calls = []
    orig = type(model)._decode_dense_gathered
    monkeypatch.setattr(type(model), "_decode_dense_gathered", lambda *a: calls.append(1) or orig(*a))
    kernel_full, kernel_steps = run()
    assert calls  # the kernel path ran
    monkeypatch.setattr(gathered_attention, "usable", lambda *t: False)
    dense_full, dense_steps = run()
    for a, b in ((kernel_full, dense_full), (kernel_steps, dense_steps)):
        assert torch.equal(torch.isfinite(a), torch.isfinite(b))
        fin = torch.isfinite(b)
        assert float((a[fin] - b[fin]).abs().max()) < 1e-5


def test_knn_kdtree_reuses_a_tree_only_for_unchanged_keys(monkeypatch):
    """The k-d trees of a key set are kept across calls (a drop-in decision searches the same map every 0.5 s) and
    rebuilt when the keys change in place, when the valid mask changes, or for other keys: the neighbours always
    equal a fresh search."""
    from r1sim_sumo.model import layers

    monkeypatch.setattr(layers, "KD_MIN_PAIRS", 0)
    monkeypatch.setattr(layers, "_TREES", [])
    built = []
    from scipy.spatial import cKDTree

    class Counting(cKDTree):
        def __init__(self, *a, **k):
            built.append(1)
            super().__init__(*a, **k)

    monkeypatch.setattr("scipy.spatial.cKDTree", Counting)
    g = torch.Generator().manual_seed(1)
    keys = torch.rand(1, 500, 2, generator=g) * 200.0
    valid = torch.ones(1, 500, dtype=torch.bool)
    q = torch.rand(1, 40, 2, generator=g) * 200.0

    def fresh(kx, kv):
        monkeypatch.setattr(layers, "KD_MIN_PAIRS", 1 << 40)
        out = layers.knn(q, kx, kv, 8, 15.0)
        monkeypatch.setattr(layers, "KD_MIN_PAIRS", 0)
        return out

    def same(a, b):
        (ai, av), (bi, bv) = a, b
        return torch.equal(av.sum(-1), bv.sum(-1)) and all(
            set(ai[0, r][av[0, r]].tolist()) == set(bi[0, r][bv[0, r]].tolist()) for r in range(q.shape[1]))

    a = layers.knn(q, keys, valid, 8, 15.0)
    b = layers.knn(q, keys[..., :2], valid, 8, 15.0)  # a new view of the same keys: the tree is reused
    assert len(built) == 1 and same(a, b) and same(a, fresh(keys, valid))
    keys[0, :250] += 50.0  # in place: rebuilt
    c = layers.knn(q, keys, valid, 8, 15.0)
    assert len(built) == 2 and same(c, fresh(keys, valid))
    valid2 = valid.clone()
    valid2[0, ::3] = False  # another mask: rebuilt
    d = layers.knn(q, keys, valid2, 8, 15.0)
    assert len(built) == 3 and same(d, fresh(keys, valid2))
    other = keys.clone()  # equal values, other memory: rebuilt
    layers.knn(q, other, valid, 8, 15.0)
    assert len(built) == 4
