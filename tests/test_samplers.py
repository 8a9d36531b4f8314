import math

import pytest
import torch

from r1sim_sumo.rollout.samplers import (
    Sampler,
    entropy_of,
    min_paper_k,
    parse_sampler,
    sample_topk_per_row,
    token_forward_m,
    token_forward_order,
    token_lateral_m,
    topk_sorted,
)


def test_entropy_known_values():
    assert entropy_of(torch.zeros(8)).item() == pytest.approx(math.log(8), rel=1e-5)
    peaked = torch.tensor([0.0] + [-1e9] * 7)
    assert entropy_of(peaked).item() == pytest.approx(0.0, abs=1e-5)
    with_inf = torch.tensor([0.0, 0.0, float("-inf"), float("-inf")])
    assert entropy_of(with_inf).item() == pytest.approx(math.log(2), rel=1e-5)


def test_paper_entropy_k_formula_and_floor():
    s = Sampler(kind="entropy", k_min=16, k_max=80)
    logits = torch.randn(1000, 256) * torch.linspace(0.1, 20, 1000)[:, None]
    out = s(logits, torch.Generator().manual_seed(0))
    # as written, K_t never goes below (k_min + k_max) / 2
    assert out.k.min().item() >= math.floor(min_paper_k(16, 80))
    assert ((out.token[:, None] == logits.topk(80, -1).indices).any(-1)).all()  # drawn within its row's top-K_t


def _rows(V: int = 256) -> torch.Tensor:
    """Rows with known entropies: one-hot (H = 0), uniform over 2 (H = ln 2), over 16 (ln 16) and over all V (ln V);
    the non-uniform rows keep finite (-1e4) logits elsewhere, so every id is valid."""
    rows = torch.full((4, V), -1e4)
    rows[0, 0] = 0.0
    rows[1, :2] = 0.0
    rows[2, :16] = 0.0
    rows[3] = 0.0
    return rows


def test_paper_entropy_k_against_hand_computed_values():
    """K_t = k_min + (k_max - k_min) / (1 + exp(-H_t)) (R1Sim), worked by hand for (16, 80):
    H = 0 -> 16 + 64 / 2 = 48; H = ln 2 -> 16 + 64 * 2/3 = 58.67 -> 59; H = ln 16 -> 16 + 64 * 16/17 = 76.2 -> 76;
    H = ln 256 -> 16 + 64 * 256/257 = 79.75 -> 80."""
    out = Sampler(kind="entropy", k_min=16, k_max=80)(_rows(), torch.Generator().manual_seed(0))
    assert out.entropy.tolist() == pytest.approx([0.0, math.log(2), math.log(16), math.log(256)], abs=1e-4)
    assert out.k.tolist() == [48, 59, 76, 80]


def test_normalised_entropy_k_against_hand_computed_values():
    """entropy-norm: K_t = k_min + (k_max - k_min) * H_t / ln(n_valid) with n_valid = 256 here:
    H = 0 -> 16; ln 2 -> 16 + 64 / 8 = 24; ln 16 -> 16 + 64 / 2 = 48; ln 256 -> 80. Unlike the paper's formula it
    reaches k_min on a peaked row; and drawn tokens stay inside the row's top-K_t."""
    rows = _rows()
    out = Sampler(kind="entropy-norm", k_min=16, k_max=80)(rows, torch.Generator().manual_seed(0))
    assert out.k.tolist() == [16, 24, 48, 80]
    # with fewer valid ids (-inf elsewhere) the normaliser is ln(n_valid): uniform over 16 of 16 valid -> k_max,
    # capped at the 16 valid ids
    few = torch.full((1, 256), float("-inf"))
    few[0, :16] = 0.0
    o2 = Sampler(kind="entropy-norm", k_min=4, k_max=80)(few, torch.Generator().manual_seed(0))
    assert o2.k.tolist() == [16] and o2.token.item() < 16
    # sampling frequencies: uniform over the 16 equal ids of row 2 (K = 48 keeps them and 32 at -1e4)
    many = rows[2:3].expand(4000, -1)
    toks = Sampler(kind="entropy-norm", k_min=16, k_max=80)(many, torch.Generator().manual_seed(1)).token
    counts = torch.bincount(toks, minlength=256)
    assert counts[16:].sum() == 0 and counts[:16].min() > 4000 / 16 * 0.6


def test_topk_never_samples_outside_topk_and_logp_is_truncated():
    g = torch.Generator().manual_seed(1)
    logits = torch.randn(5000, 50, generator=g)
    out = Sampler(kind="topk", k=3)(logits, g)
    top3 = logits.topk(3, -1).indices
    assert (top3 == out.token[:, None]).any(-1).all()
    # log-prob is under the renormalised top-3 distribution
    lp_full = torch.log_softmax(logits, -1).gather(-1, out.token[:, None]).squeeze(-1)
    lse3 = torch.logsumexp(logits.topk(3, -1).values, -1)
    lp_trunc = logits.gather(-1, out.token[:, None]).squeeze(-1) - lse3
    assert torch.allclose(out.logp, lp_trunc, atol=1e-5)
    assert (out.logp >= lp_full - 1e-6).all()


def test_sampling_frequencies_match_truncated_distribution():
    logits = torch.log(torch.tensor([0.5, 0.3, 0.15, 0.05]))
    out = sample_topk_per_row(logits.expand(40000, 4), torch.tensor(2), generator=torch.Generator().manual_seed(2))
    freq0 = (out.token == 0).float().mean().item()
    assert freq0 == pytest.approx(0.5 / 0.8, abs=0.01)
    assert set(out.token.unique().tolist()) == {0, 1}


def test_greedy_and_temperature():
    logits = torch.tensor([[0.0, 2.0, 1.0]])
    assert Sampler(kind="greedy")(logits).token.item() == 1
    g = torch.Generator().manual_seed(3)
    cold = Sampler(kind="topk", k=3, temperature=0.05)(logits.expand(2000, 3), g)
    assert (cold.token == 1).float().mean() > 0.99


def test_invalid_ids_never_sampled_and_nan_rows_fall_back():
    logits = torch.randn(1000, 10)
    logits[:, 5:] = float("-inf")
    out = Sampler(kind="topk", k=8)(logits, torch.Generator().manual_seed(4))
    assert (out.token < 5).all() and (out.k == 5).all()
    bad = torch.full((2, 10), float("nan"))
    out = Sampler(kind="entropy")(bad)
    assert (out.token == 0).all() and torch.isfinite(out.logp).all()


@pytest.mark.parametrize("spec,kind", [("greedy", "greedy"), ("topk:32", "topk"), ("entropy:16,80", "entropy"), ("entropy-norm:8,64@0.7", "entropy-norm"), ("intent:0.3", "intent"), ("intent:0.5@2", "intent")])
def test_parse_roundtrip(spec, kind):
    s = parse_sampler(spec)
    assert s.kind == kind and parse_sampler(s.spec) == s


@pytest.mark.parametrize("bad", ["topk", "topk:0", "entropy:80,16", "beam:3", "topk:32@-1", "topk:x", "intent", "intent:0", "intent:-1", "intent:x"])
def test_parse_rejects(bad):
    with pytest.raises(ValueError, match="sampler"):
        parse_sampler(bad)


@pytest.mark.parametrize("k", [1, 5, 16, 80, 127, 128, 300])
def test_two_stage_topk_equals_torch_topk(k):
    g = torch.Generator().manual_seed(k)
    x = torch.randn(64, 2048, generator=g) * 3
    x[::3, 512:] = float("-inf")  # rows of a smaller vocabulary
    x[5, 7:] = float("-inf")  # fewer finite ids than k
    vals, idx = topk_sorted(x, k)
    ref_vals, _ = torch.topk(x, k, dim=-1)
    assert torch.equal(vals, ref_vals)  # same values in the same (descending) order
    assert torch.equal(torch.gather(x, -1, idx), vals)  # the indices point at those values
    finite = torch.isfinite(vals)
    for r in range(x.shape[0]):  # no index picked twice among the finite picks
        assert idx[r][finite[r]].unique().numel() == int(finite[r].sum())


def test_k_is_clamped_to_the_number_of_valid_ids():
    logits = torch.full((3, 2048), float("-inf"))
    logits[:, :4] = torch.tensor([1.0, 2.0, 3.0, 4.0])
    out = Sampler(kind="topk", k=80)(logits, torch.Generator().manual_seed(0))
    assert out.k.tolist() == [4, 4, 4] and (out.token < 4).all()


@pytest.mark.parametrize("spec", ["topk:5", "topk:40@0.7", "greedy", "topk:1", "topk:600", "entropy:16,80"])
def test_draw_gives_the_same_tokens_as_the_full_sampler(spec):
    """Sampler.draw (tokens only, no full log-softmax / entropy) draws exactly what __call__ draws, bad rows included."""
    s = parse_sampler(spec)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 64, 2048, generator=g) * 3
    x[0, ::7, 11] = float("nan")  # NaN somewhere in a row: falls back to token 0
    x[1, :4] = float("-inf")  # no valid id: token 0
    x[1, 8:16, 30:] = float("-inf")  # fewer valid ids than k
    with pytest.warns(RuntimeWarning):
        a = s(x, torch.Generator().manual_seed(3)).token
    with pytest.warns(RuntimeWarning):
        b = s.draw(x, torch.Generator().manual_seed(3))
    assert torch.equal(a, b)
    assert (b[0, ::7] == 0).all() and (b[1, :4] == 0).all() and (b[1, 8:16] < 30).all()


def test_blocked_max_equals_torch_max_with_nan_inf_and_ties():
    """The greedy draw's two-stage maximum: same values and indices as ``max(-1)``, first index among ties, a NaN
    row's NaN found, an all ``-inf`` row at index 0; widths that the blocks do not divide fall back to ``max``."""
    from r1sim_sumo.rollout.samplers import max_blocked

    g = torch.Generator().manual_seed(0)
    for shape in [(1, 70, 3720), (2, 5, 2048), (3, 7, 360), (2, 3, 5), (4, 1001)]:
        x = torch.randn(*shape, generator=g)
        v, i = max_blocked(x)
        v0, i0 = x.max(-1, keepdim=True)
        assert torch.equal(v, v0) and torch.equal(i, i0), shape
    x = torch.randn(1, 9, 3720, generator=g)
    x[0, 3, 100] = float("nan")
    x[0, 5] = float("-inf")
    x[0, 7, 17:24] = 9.0  # a tie inside one block and across blocks: the first one wins
    x[0, 7, 40] = 9.0
    x[0, 8, 3719] = 9.0  # the last entry
    v, i = max_blocked(x)
    assert i[0, :, 0].tolist()[3:] == [100, int(x[0, 4].argmax()), 0, int(x[0, 6].argmax()), 17, 3719]
    assert math.isnan(v[0, 3, 0]) and v[0, 5, 0] == float("-inf")


# ---------------------------------------------------------------------------- lateral intent


def _intent_case():
    """Six tokens ending at lateral offsets [m] -1, -0.4, -0.1, 0, 0.1, 0.6 (left positive); the mode is the 0 m
    one; sides at 0.25 m: right = ids 0, 1 (p 0.03 + 0.05), kept = ids 2, 3, 4 (0.12 + 0.6 + 0.1), left = id 5 (0.1)."""
    p = torch.tensor([0.03, 0.05, 0.12, 0.6, 0.1, 0.1])
    lateral = torch.tensor([-1.0, -0.4, -0.1, 0.0, 0.1, 0.6])
    return p.log(), lateral


def test_intent_draws_each_side_with_its_total_probability_and_its_best_token():
    logits, lateral = _intent_case()
    n = 40000
    out = Sampler(kind="intent", lateral_m=0.25)(logits.expand(n, 6), torch.Generator().manual_seed(5),
                                                  lateral.expand(n, 6))
    # within a side only its most likely token: id 1 (right), 3 (kept), 5 (left); never 0, 2, 4
    assert set(out.token.unique().tolist()) == {1, 3, 5}
    freq = {t: (out.token == t).float().mean().item() for t in (1, 3, 5)}
    assert freq[1] == pytest.approx(0.08, abs=0.006)  # right: 0.03 + 0.05
    assert freq[3] == pytest.approx(0.82, abs=0.008)  # kept: 0.12 + 0.6 + 0.1
    assert freq[5] == pytest.approx(0.10, abs=0.006)
    # logp = log of the side's probability; logp_full = the token's own
    side_p = {1: 0.08, 3: 0.82, 5: 0.10}
    for t, sp in side_p.items():
        m = out.token == t
        assert torch.allclose(out.logp[m], torch.tensor(math.log(sp)), atol=1e-5)
        assert torch.allclose(out.logp_full[m], logits[t], atol=1e-5)
    assert (out.k == 3).all()


def test_intent_sides_are_measured_from_the_mode_not_from_zero():
    """On a curve the most likely token already ends 2 m to the left: a token 0.1 m from it is kept, not 'left'."""
    logits, lateral = _intent_case()
    out = Sampler(kind="intent", lateral_m=0.25)(logits.expand(20000, 6), torch.Generator().manual_seed(6),
                                                 (lateral + 2.0).expand(20000, 6))
    assert set(out.token.unique().tolist()) == {1, 3, 5}
    wide = Sampler(kind="intent", lateral_m=5.0)(logits.expand(2000, 6), torch.Generator().manual_seed(7),
                                                 lateral.expand(2000, 6))
    assert (wide.token == 3).all() and (wide.k == 1).all()  # one side only: greedy decoding exactly


def test_intent_temperature_and_invalid_ids():
    logits, lateral = _intent_case()
    logits = torch.cat([logits, torch.tensor([float("-inf")])])  # id 6 invalid, far to the left
    lateral = torch.cat([lateral, torch.tensor([3.0])])
    n = 20000
    cold = Sampler(kind="intent", lateral_m=0.25, temperature=0.05)(logits.expand(n, 7), torch.Generator().manual_seed(8),
                                                                     lateral.expand(n, 7))
    assert (cold.token == 3).float().mean() > 0.999
    out = Sampler(kind="intent", lateral_m=0.25)(logits.expand(n, 7), torch.Generator().manual_seed(9), lateral.expand(n, 7))
    assert not (out.token == 6).any()
    with pytest.raises(ValueError, match="lateral"):
        Sampler(kind="intent")(logits[None])


def _synthetic_vocab():
    from r1sim_sumo.model.synthetic import synthetic_vocab
    from r1sim_sumo.tokens.motion_vocab import MotionVocab

    return MotionVocab.from_traj({i: t.numpy() for i, t in enumerate(synthetic_vocab((64, 16, 16)))})


@pytest.mark.parametrize("read, axis", [(token_lateral_m, 1), (token_forward_m, 0)])
def test_token_ends_are_read_per_type_from_the_vocabulary(read, axis):
    """intent reads each token's lateral end (y), median its forward travel (x), per agent type (padding: vehicle)."""
    vocab = _synthetic_vocab()
    at = torch.tensor([[0, 1, 2, -1]])
    end = read(vocab, at)
    assert end.shape == (1, 4, vocab.max_size)
    for j, t in enumerate([0, 1, 2, 0]):
        n = vocab.size(t)
        assert torch.allclose(end[0, j, :n], torch.as_tensor(vocab.traj[t][:, -1, axis]))


def test_intent_sides_leave_only_the_side_the_route_asks_for():
    """sides +1: left or kept only (right's probability stays with the kept side); 0: greedy; -1: right or kept."""
    logits, lateral = _intent_case()
    n = 30000
    sides = torch.tensor([1, 0, -1]).repeat_interleave(n)
    out = Sampler(kind="intent", lateral_m=0.25)(logits.expand(3 * n, 6), torch.Generator().manual_seed(10),
                                                  lateral.expand(3 * n, 6), sides)
    left, none, right = out.token[:n], out.token[n:2 * n], out.token[2 * n:]
    assert set(left.unique().tolist()) == {3, 5} and (left == 5).float().mean().item() == pytest.approx(0.10, abs=0.006)
    assert (none == 3).all()
    assert set(right.unique().tolist()) == {1, 3} and (right == 1).float().mean().item() == pytest.approx(0.08, abs=0.006)
    assert torch.allclose(out.logp[n:2 * n], torch.zeros(n), atol=1e-6)  # kept side holds all probability
    assert (out.k[n:2 * n] == 1).all() and (out.k[:n] == 2).all()


def _moving_off_case():
    """One agent at a standstill: "stay" (0 m travel) is the single most likely token (p 0.30), while 0.70 of the
    probability is spread over six moving-off tokens (0.3-1.8 m travel, 0.1 or 0.15 each), one with a lateral twin."""
    fwd = torch.tensor([0.0, 0.3, 0.6, 0.62, 0.9, 1.2, 1.8])
    p = torch.tensor([0.30, 0.10, 0.15, 0.05, 0.15, 0.15, 0.10])
    return p.log(), fwd


def test_median_takes_the_most_likely_token_at_the_median_travel_where_greedy_keeps_standing():
    logits, fwd = _moving_off_case()
    greedy = Sampler(kind="greedy")(logits[None])
    assert greedy.token.item() == 0  # the mode stands still
    # cumulative over the sorted travel: 0.30, 0.40, 0.55 -> the median travel is 0.6 m; within 0.1 m: ids 2 and 3
    out = Sampler(kind="median", forward_m=0.1)(logits[None], token_forward=fwd[None])
    assert out.token.item() == 2 and out.k.item() == 2
    assert out.logp.item() == 0.0  # deterministic
    assert out.logp_full.item() == pytest.approx(math.log(0.15), rel=1e-5)
    # a window of 0 keeps the median token itself; a wide one (2 m) holds all of them: greedy again
    assert Sampler(kind="median", forward_m=0.0)(logits[None], token_forward=fwd[None]).token.item() == 2
    assert Sampler(kind="median", forward_m=2.0)(logits[None], token_forward=fwd[None]).token.item() == 0


def test_median_is_greedy_on_a_distribution_centred_on_its_mode_and_skips_invalid_ids():
    fwd = torch.tensor([4.0, 4.5, 5.0, 5.5, 6.0, 9.0])
    logits = torch.tensor([0.1, 0.2, 0.4, 0.2, 0.1, 1.0]).log()
    logits[5] = float("-inf")  # invalid for this type: never the median, never chosen
    out = Sampler(kind="median", forward_m=0.1)(logits.expand(3, 6), token_forward=fwd.expand(3, 6))
    assert (out.token == 2).all()
    assert (out.token == Sampler(kind="greedy")(logits.expand(3, 6)).token).all()
    with pytest.raises(ValueError, match="forward travel"):
        Sampler(kind="median")(logits[None])


def test_median_temperature_moves_the_median_and_draw_matches_call():
    logits, fwd = _moving_off_case()
    cold = Sampler(kind="median", forward_m=0.1, temperature=0.2)  # sharpened: "stay" holds more than half
    assert cold(logits[None], token_forward=fwd[None]).token.item() == 0
    s = parse_sampler("median:0.1")
    assert s == Sampler(kind="median", forward_m=0.1) and s.spec == "median:0.1"
    assert parse_sampler("median:0.2@0.5").spec == "median:0.2@0.5"
    with pytest.raises(ValueError, match="median"):
        parse_sampler("median:-1")
    rows = torch.randn(50, 7)
    f = fwd.expand(50, 7)
    assert torch.equal(s.draw(rows, token_forward=f), s(rows, token_forward=f).token)


def test_token_inputs_give_each_rule_the_geometry_it_reads():
    vocab, at = _synthetic_vocab(), torch.tensor([[0, 1, 2, -1]])
    assert torch.equal(parse_sampler("median:0.1").token_inputs(vocab, at)["token_forward"], token_forward_m(vocab, at))
    inputs = parse_sampler("median:0.1").token_inputs(vocab, at)
    assert set(inputs) == {"token_forward", "token_forward_order"}
    ordered = torch.gather(inputs["token_forward"], -1, inputs["token_forward_order"])
    assert (ordered.diff(dim=-1) >= 0).all()  # each agent's ids ascending in forward travel (cached per type)
    assert torch.equal(token_forward_order(vocab, at), inputs["token_forward_order"])
    # the cached order gives the same tokens as sorting each row, on the drop-in's fast path and in __call__
    s, logits = parse_sampler("median:0.1"), torch.randn(1, 4, vocab.max_size) * 3
    logits[0, :, 64:] = float("-inf")  # ids beyond the smaller types' vocabularies stay invalid for all
    fast = s.draw(logits, **inputs)
    assert torch.equal(fast, s(logits, token_forward=inputs["token_forward"]).token)
    assert torch.equal(fast, s(logits, **inputs).token)
    assert set(parse_sampler("intent:0.25").token_inputs(vocab, at)) == {"token_lateral"}
    assert parse_sampler("topk:5").token_inputs(vocab, at) == {}


def test_quantile_centres_the_median_rule_on_a_higher_travel_quantile_and_parses():
    logits, fwd = _moving_off_case()
    # cumulative over the sorted travel: 0.30, 0.40, 0.55, 0.60, 0.75, 0.90, 1.0
    # q 0.7 -> 0.9 m (0.75 is the first >= 0.7); within 0.1 m only id 4; q 0.8 -> 1.2 m (id 5)
    s70 = parse_sampler("quantile:0.7,0.1")
    assert s70 == Sampler(kind="median", forward_m=0.1, quantile=0.7) and s70.spec == "quantile:0.7,0.1"
    assert s70(logits[None], token_forward=fwd[None]).token.item() == 4
    assert parse_sampler("quantile:0.8,0.1")(logits[None], token_forward=fwd[None]).token.item() == 5
    # draw() (the drop-in's path) takes the same token; quantile 0.5 is the median rule exactly
    assert s70.draw(logits[None], token_forward=fwd[None]).item() == 4
    assert parse_sampler("quantile:0.5,0.1") == parse_sampler("median:0.1")
    assert parse_sampler("quantile:0.5,0.1").spec == "median:0.1"
    assert parse_sampler("quantile:0.6,0.2@0.5").spec == "quantile:0.6,0.2@0.5"
    for bad in ("quantile:1.0,0.1", "quantile:0,0.1", "quantile:0.6", "quantile:0.6,-1"):
        with pytest.raises(ValueError, match="quantile:0.6,0.1"):
            parse_sampler(bad)


def test_per_row_quantile_overrides_the_rules_own_in_call_and_draw():
    """The drop-in's free-road quantile: each row may be decoded at its own travel quantile (same ids as the
    equivalent whole-sampler rules, row by row)."""
    logits, fwd = _moving_off_case()
    rows, fwd2 = torch.stack([logits, logits, logits]), torch.stack([fwd, fwd, fwd])
    med = parse_sampler("median:0.1")
    q = torch.tensor([0.5, 0.7, 0.8])
    want = [med(logits[None], token_forward=fwd[None]).token.item(), 4, 5]
    assert want[0] not in (4, 5)  # the median row differs from the two raised ones
    assert med(rows, token_forward=fwd2, quantile=q).token.tolist() == want
    assert med.draw(rows, token_forward=fwd2, quantile=q).tolist() == want
    # without per-row quantiles every row keeps the rule's own
    assert med.draw(rows, token_forward=fwd2).tolist() == [want[0]] * 3
