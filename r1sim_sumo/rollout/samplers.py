"""Token samplers: greedy, fixed top-K, entropy-guided adaptive top-K (R1Sim), temperature, lateral intent, median travel.

Every sampler maps logits ``[..., V]`` (invalid ids already at ``-inf``) to a :class:`SampleOut` holding the
chosen token, the sampler's own log-probability of it (under the truncated, tempered distribution actually
sampled from — GRPO's "old" log-prob), the Shannon entropy ``H_t`` [nats] of the full model distribution and the
``K_t`` used.

Entropy-guided adaptive top-K (paper, Eq. K_t): ``K_t = k_min + (k_max - k_min) / (1 + exp(-H_t))``. Because
``H_t >= 0`` the sigmoid is >= 0.5, so as written ``K_t`` never drops below ``(k_min + k_max) / 2``; the
``normalised`` variant uses ``K_t = k_min + (k_max - k_min) * H_t / log(V)`` which spans the whole range.
Lateral intent (``intent:D``): greedy decoding hides every manoeuvre whose per-step probability never makes its
token the most likely one (a merge from an acceleration lane is started in one of several 0.5 s steps, each with a
small probability), and full sampling brings it back together with lateral noise that adds up to lane changes nobody
asked for. ``intent`` samples only the side: each token is *left*, *right* or *kept* by where it ends sideways
(its lateral offset at 0.5 s, [m], agent frame, left positive) against the most likely token's (beyond ``D`` metres
either side, or within), the side is drawn from the model's total probability of each (tempered), and within the
side the most likely token is taken. Where the kept side is drawn (almost always) this is greedy decoding exactly.
It needs each token's lateral offset: :func:`token_lateral_m`. Measured (session 42, docs/simulate/gate_s42): the
policy gives lane keepers about as much side probability per step as agents whose lane ends, so ``intent:0.25`` makes
0.515 of the acceleration-lane agents merge (greedy 0.211, log 0.658) and 0.387 of the lane keepers change lanes
(greedy 0.028); an option, not a default anywhere.

Median travel (``median:D``): greedy decoding takes the mode of the next token, and where the model spreads a manoeuvre
over many tokens (moving off from a standstill, speeding up towards the desired speed: every acceleration a little
likely) while one token holds "keep what you do" the mode keeps it, step after step, though most of the probability
says "faster". ``median`` is deterministic like greedy but central in the travel: it takes the probability-weighted
median of the tokens' forward travel at 0.5 s ([m], agent frame, x forward; the full distribution at temperature 1,
or the tempered one with ``@T``) and, among the tokens ending within ``D`` metres of it along x, the most likely one
(so the lateral and heading choice stays the mode's among those). Where the distribution is symmetric about its
mode this is greedy decoding; it needs each token's forward travel: :func:`token_forward_m`. The position drive's
default since session 47 (``r1sim simulate --sampler median:0.1``, docs/simulate/sampler_s47); GRPO refuses it
(deterministic). ``quantile:Q,D`` centres the same rule on the ``Q`` quantile of the travel instead of the median
(``quantile:0.5,D`` is ``median:D``): the commands drive's default since session 53 with ``Q = 0.7``
(docs/simulate/quantile_s53): the policy continues its previous token's speed rather than its trend, so the median
gives back part of every speed-up, while SUMO's own checks keep each commanded speed safe.

Spec strings (CLI/config): ``greedy``, ``topk:32``, ``entropy:16,80``, ``entropy-norm:16,80``, ``intent:0.25``,
``median:0.1``, ``quantile:0.7,0.1``, with an optional ``@T`` temperature suffix (``topk:32@0.8``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch


class SampleOut(NamedTuple):
    token: torch.Tensor  # [...] int64
    logp: torch.Tensor  # [...] float32, log-prob under the sampled (truncated, tempered) distribution
    entropy: torch.Tensor  # [...] float32, entropy [nats] of the full model distribution at temperature 1
    k: torch.Tensor  # [...] int64, number of candidates kept (V_valid for untruncated)
    logp_full: torch.Tensor | None = None  # [...] float32, full-softmax log-prob of the token (temperature 1)


def token_lateral_m(vocab, agent_type: torch.Tensor) -> torch.Tensor:
    """Each token's lateral offset at its end (0.5 s) [m], in the start pose's frame (x forward, y left), per agent:
    ``[..., V_max]`` float32 for ``agent_type [...]`` (int64; negative = padding, read as a vehicle). Ids beyond a
    type's vocabulary are 0 (their logits are ``-inf`` anyway). What :class:`Sampler` ``intent`` reads."""
    traj, _, _ = vocab.torch_tables(agent_type.device)  # [3, V, 6, 3]
    return traj[:, :, -1, 1][agent_type.clamp(min=0)]


def token_forward_m(vocab, agent_type: torch.Tensor) -> torch.Tensor:
    """Each token's forward travel at its end (0.5 s) [m], in the start pose's frame (x forward), per agent:
    ``[..., V_max]`` float32 for ``agent_type [...]`` (int64; negative = padding, read as a vehicle). Ids beyond a
    type's vocabulary are 0 (their logits are ``-inf`` anyway). What :class:`Sampler` ``median`` reads."""
    traj, _, _ = vocab.torch_tables(agent_type.device)  # [3, V, 6, 3]
    return traj[:, :, -1, 0][agent_type.clamp(min=0)]


def token_forward_order(vocab, agent_type: torch.Tensor) -> torch.Tensor:
    """Each agent's token ids sorted by forward travel (:func:`token_forward_m`, ascending): ``[..., V_max]`` int64,
    from one argsort per agent type cached with the vocabulary's torch tables (sorting every row at every decision
    made a 700-vehicle drop-in draw about twice as slow: ``benchmarks/probe_greedy_max.py --samplers``). What
    :class:`Sampler` ``median`` walks along."""
    traj, _, _ = vocab.torch_tables(agent_type.device)  # [3, V, 6, 3]
    cache = getattr(vocab, "_torch_cache", None)
    key = ("forward_order", str(agent_type.device))
    order = cache.get(key) if cache is not None else None
    if order is None:
        order = traj[:, :, -1, 0].argsort(dim=-1, stable=True)  # [3, V]
        if cache is not None:
            cache[key] = order
    return order[agent_type.clamp(min=0)]


class _Prepared(NamedTuple):
    logits: torch.Tensor  # [..., V] float32, bad rows replaced by "token 0 only"
    logp: torch.Tensor  # [..., V] full log-softmax (temperature 1)
    entropy: torch.Tensor  # [...] [nats]


def _prepare(logits: torch.Tensor) -> _Prepared:
    """One pass over the logits: guard, log-softmax and entropy.

    Rows with a NaN or without any finite logit get a NaN log-softmax; they fall back to token 0 (standing
    still) with a warning, so a numerical fault in the model never crashes a rollout.
    """
    logits = logits.float()
    logp = torch.log_softmax(logits, dim=-1)
    bad = torch.isnan(logp[..., 0])  # a NaN anywhere (or no finite entry) makes the whole row NaN
    if bool(bad.any()):
        _warn_fallback(bad, stacklevel=4)
        fallback = torch.full_like(logits, float("-inf"))
        fallback[..., 0] = 0.0
        logits = torch.where(bad[..., None], fallback, logits)
        logp = torch.log_softmax(logits, dim=-1)
    return _Prepared(logits, logp, _entropy(logp))


def _warn_fallback(bad: torch.Tensor, stacklevel: int) -> None:
    import warnings

    warnings.warn(f"sampler: {int(bad.sum())} row(s) of NaN / all -inf logits fall back to token 0 (standing still)",
                  RuntimeWarning, stacklevel=stacklevel)


def _draw_from_top(top_vals: torch.Tensor, top_idx: torch.Tensor, k: torch.Tensor, temperature: float,
                   generator: torch.Generator | None):
    """Draw from the ``k`` best of each row's sorted candidates ``top_vals / top_idx [..., kmax]`` (never more than
    its valid ones), tempered: returns ``(token, choice, logp_trunc, k)``, ``logp_trunc [..., kmax]`` the
    log-probabilities of the truncated, tempered distribution and ``choice`` the rank drawn."""
    k = torch.minimum(k, (top_vals > float("-inf")).sum(-1).clamp(min=1))  # never more than the valid ids
    rank = torch.arange(top_vals.shape[-1], device=top_vals.device)
    scaled = (top_vals / max(temperature, 1e-6)).masked_fill_(rank >= k[..., None], float("-inf"))
    logp_trunc = torch.log_softmax(scaled, dim=-1)
    flat = logp_trunc.reshape(-1, logp_trunc.shape[-1]).exp()
    choice = torch.multinomial(flat, 1, generator=generator).reshape(k.shape)  # [...]
    token = torch.gather(top_idx, -1, choice[..., None]).squeeze(-1)
    return token, choice, logp_trunc, k


def _n_valid(logits: torch.Tensor) -> torch.Tensor:
    """Number of finite logits per row (the ids the sampler may pick)."""
    return (logits > float("-inf")).sum(-1)


def _entropy(logp: torch.Tensor) -> torch.Tensor:
    p = logp.exp()
    return -(p * logp).nan_to_num_(0.0, 0.0, 0.0).sum(-1)  # p = 0 where logp = -inf: 0 * -inf = nan -> 0


def topk_sorted(x: torch.Tensor, k: int, block: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """``torch.topk(x, k, -1)`` (largest, sorted) computed in two cheaper stages for wide rows.

    The k largest entries of a row lie in the k blocks (of ``block`` columns) with the largest block maxima:
    each of those k maxima is a distinct entry >= the k-th block maximum, so the k-th largest entry is too, and
    any entry at least that large lifts its block's maximum to it. So: block maxima, top-k blocks, then top-k
    of their ``k * block`` entries. Same values and order as ``torch.topk`` (ties between equal values may pick
    other indices); about 2x faster for 2048-wide rows and k = 80 on CPU.
    """
    V = x.shape[-1]
    nb = V // block
    if k * block * 2 > V or V % block or k > nb:
        return torch.topk(x, min(k, V), dim=-1)
    lead = x.shape[:-1]
    xb = x.reshape(-1, nb, block)  # [R, nb, block]
    # block maxima (NaN propagates, as in amax): max_pool1d is ~3x faster than amax over an inner dim of 8 on CPU
    bmax = torch.nn.functional.max_pool1d(x.reshape(-1, 1, V), block).reshape(-1, nb) if x.is_floating_point() else xb.amax(-1)
    _, bi = torch.topk(bmax, k, dim=-1, sorted=False)  # [R, k] best blocks
    cand = torch.gather(xb, 1, bi[..., None].expand(-1, -1, block)).reshape(-1, k * block)  # [R, k*block]
    vals, ci = torch.topk(cand, k, dim=-1)
    idx = torch.gather(bi, 1, ci // block) * block + ci % block
    return vals.reshape(lead + (k,)), idx.reshape(lead + (k,))


def max_blocked(x: torch.Tensor, block: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """``x.max(-1, keepdim=True)`` (values and indices ``[..., 1]``) in two cheaper stages for wide rows: the block
    maxima (``max_pool1d``, vectorised), the best block, then the best of its ``block`` entries. The same value and,
    as torch's CPU ``max`` does, the first index among equal maxima; a NaN in a row is its maximum, as in ``max``.
    About 2.5x faster than ``max`` over 700 x 3,720 logits on 2 CPU threads (the drop-in's greedy decision)."""
    V = x.shape[-1]
    if V % block or V < 4 * block or not x.is_floating_point() or x.numel() == 0:
        return x.max(-1, keepdim=True)
    lead, nb = x.shape[:-1], V // block
    xb = x.reshape(-1, nb, block)  # [R, nb, block]
    bmax = torch.nn.functional.max_pool1d(x.reshape(-1, 1, V), block).reshape(-1, nb)  # [R, nb]
    bi = bmax.max(-1).indices  # [R] best block (NaN ranks first)
    cand = torch.gather(xb, 1, bi[:, None, None].expand(-1, 1, block)).reshape(-1, block)  # [R, block]
    val, ci = cand.max(-1)
    return val.reshape(lead + (1,)), (bi * block + ci).reshape(lead + (1,))


def entropy_of(logits: torch.Tensor) -> torch.Tensor:
    """Shannon entropy [nats] of softmax(logits) over the last dim; ``-inf`` entries contribute 0."""
    return _prepare(logits).entropy


def _sample_prepared(pr: _Prepared, k: torch.Tensor, temperature: float, generator: torch.Generator | None) -> SampleOut:
    V = pr.logits.shape[-1]
    k = torch.as_tensor(k, device=pr.logits.device).expand_as(pr.entropy).clamp(min=1)
    kmax = int(k.max()) if k.numel() else 1
    top_vals, top_idx = topk_sorted(pr.logits, min(kmax, V))  # [..., kmax]
    token, choice, logp_trunc, k = _draw_from_top(top_vals, top_idx, k, temperature, generator)
    logp = torch.gather(logp_trunc, -1, choice[..., None]).squeeze(-1)
    logp_full = torch.gather(pr.logp, -1, token[..., None]).squeeze(-1)
    return SampleOut(token, logp, pr.entropy, k, logp_full)


def sample_topk_per_row(logits: torch.Tensor, k: torch.Tensor, temperature: float = 1.0, generator: torch.Generator | None = None) -> SampleOut:
    """Sample from the top-``k`` logits of each row, ``k`` an int64 tensor broadcastable to ``logits[..., 0]``."""
    return _sample_prepared(_prepare(logits), k, temperature, generator)


def _median_token(logits: torch.Tensor, forward: torch.Tensor, order: torch.Tensor | None, window_m: float,
                  temperature: float, count: bool = False, quantile: float | torch.Tensor = 0.5):
    """The most likely token among those whose forward travel lies within ``window_m`` of the (tempered)
    distribution's probability-weighted ``quantile`` of travel (0.5: the median; module docstring): ``[...]`` int64
    for ``logits [..., V]`` (finite somewhere in every row), ``forward [..., V]`` [m] and its ascending ``order``
    (argsorted when None). ``quantile``: one for every row, or ``[...]`` one per row. ``count``: also the number of
    valid tokens within the window ``[...]``."""
    if isinstance(quantile, torch.Tensor):
        quantile = quantile.to(logits.dtype)[..., None]  # [..., 1]
    fwd = forward.to(logits.dtype).expand_as(logits)
    if order is None:
        order = fwd.argsort(-1)
    p = (logits / max(temperature, 1e-6)).softmax(-1)  # -inf ids: 0
    cum = torch.gather(p, -1, order.expand_as(logits)).cumsum_(-1)
    # the first sorted position whose cumulative probability reaches the quantile: a token of positive probability
    at = (cum < quantile * cum[..., -1:]).sum(-1, keepdim=True).clamp_(max=logits.shape[-1] - 1)
    med = torch.gather(fwd, -1, torch.gather(order.expand_as(logits), -1, at))  # [..., 1] [m]
    far = (fwd - med).abs_() > window_m  # the median token itself is never far
    token = logits.masked_fill(far, float("-inf")).argmax(-1)
    if not count:
        return token
    return token, (~far & torch.isfinite(logits)).sum(-1)


@dataclass(frozen=True)
class Sampler:
    """A token-sampling rule. ``kind`` in {"greedy", "topk", "entropy", "entropy-norm", "full", "intent", "median"}."""

    kind: str = "entropy"
    k: int = 32  # fixed top-K
    k_min: int = 16  # entropy-guided lower bound
    k_max: int = 80  # entropy-guided upper bound
    temperature: float = 1.0
    lateral_m: float = 0.25  # intent: a token ending this far [m] beside the most likely one's end is a side move
    forward_m: float = 0.1  # median: tokens ending within this far [m] along x of the median travel are candidates
    quantile: float = 0.5  # median: the travel quantile the candidates are centred on (0.5: the median; ``quantile:Q,D``)

    @property
    def needs_lateral(self) -> bool:
        """The rule reads each token's lateral offset (``token_lateral`` of :meth:`__call__`)."""
        return self.kind == "intent"

    def token_inputs(self, vocab, agent_type: torch.Tensor) -> dict:
        """The per-token geometry this rule reads, as keyword arguments of :meth:`__call__` / :meth:`draw` for agents
        of ``agent_type [...]``: ``token_lateral`` (intent), ``token_forward`` (median), nothing for the others."""
        if self.kind == "intent":
            return {"token_lateral": token_lateral_m(vocab, agent_type)}
        if self.kind == "median":
            return {"token_forward": token_forward_m(vocab, agent_type),
                    "token_forward_order": token_forward_order(vocab, agent_type)}
        return {}

    def choose_k(self, logits: torch.Tensor, entropy: torch.Tensor, n_valid: torch.Tensor | None = None) -> torch.Tensor:
        if self.kind == "topk":
            return torch.full(entropy.shape, self.k, dtype=torch.long, device=entropy.device)
        if self.kind == "entropy":
            kf = self.k_min + (self.k_max - self.k_min) * torch.sigmoid(entropy)
            return kf.round().long()
        if n_valid is None:
            n_valid = _n_valid(logits)
        if self.kind == "entropy-norm":
            h_norm = entropy / torch.log(n_valid.clamp(min=2).float())
            return (self.k_min + (self.k_max - self.k_min) * h_norm.clamp(0, 1)).round().long()
        if self.kind == "full":
            return n_valid
        raise ValueError(f"unknown sampler kind '{self.kind}'")

    def __call__(self, logits: torch.Tensor, generator: torch.Generator | None = None,
                 token_lateral: torch.Tensor | None = None, sides: torch.Tensor | None = None,
                 token_forward: torch.Tensor | None = None, token_forward_order: torch.Tensor | None = None,
                 quantile: torch.Tensor | None = None) -> SampleOut:
        """Sample ``logits [..., V]``. ``intent`` only: ``token_lateral [..., V]`` [m] (:func:`token_lateral_m`), and
        optionally ``sides [...]`` int, the side each agent may move to (+1 left, -1 right, 0 neither: greedy
        decoding; the drop-in's route says which), all sides where not given. ``median`` only: ``token_forward
        [..., V]`` [m] (:func:`token_forward_m`) and optionally its ascending order (:func:`token_forward_order`;
        sorted here when not given), and optionally ``quantile [...]`` in (0, 1), each row's travel quantile in place
        of the rule's own (the drop-in's free-road quantile). :meth:`token_inputs` gives the rule's geometry."""
        pr = _prepare(logits)
        if self.kind == "intent":
            if token_lateral is None:
                raise ValueError("sampler 'intent' needs each token's lateral offset (token_lateral_m(vocab, agent_type))")
            return self._intent(pr, token_lateral, generator, sides)
        if self.kind == "median":
            if token_forward is None:
                raise ValueError("sampler 'median' needs each token's forward travel (token_forward_m(vocab, agent_type))")
            token, k = _median_token(pr.logits, token_forward, token_forward_order, self.forward_m, self.temperature,
                                     count=True, quantile=self.quantile if quantile is None else quantile)
            logp_full = torch.gather(pr.logp, -1, token[..., None]).squeeze(-1)
            return SampleOut(token, torch.zeros_like(pr.entropy), pr.entropy, k, logp_full)
        if self.kind == "greedy":
            token = pr.logits.argmax(-1)
            logp_full = torch.gather(pr.logp, -1, token[..., None]).squeeze(-1)
            return SampleOut(token, torch.zeros_like(pr.entropy), pr.entropy, torch.ones_like(token), logp_full)
        return _sample_prepared(pr, self.choose_k(pr.logits, pr.entropy), self.temperature, generator)

    def _intent(self, pr: _Prepared, lateral: torch.Tensor, generator: torch.Generator | None,
                sides: torch.Tensor | None = None) -> SampleOut:
        """Draw the side (left / kept / right of the most likely token's end, see the module docstring) from its
        tempered total probability, then the most likely token of that side. ``sides`` (``[...]``, +1 / -1 / 0)
        leaves only the kept side and the one named: a side not allowed keeps its probability with the kept side.
        ``logp`` is the drawn side's log-probability (the chance this token was drawn), ``k`` the number of sides
        with any probability."""
        lateral = lateral.to(pr.logits.dtype)
        mode = pr.logits.argmax(-1, keepdim=True)
        off = lateral.expand_as(pr.logits) - torch.gather(lateral.expand_as(pr.logits), -1, mode)  # beside the mode [m]
        left, right = off > self.lateral_m, off < -self.lateral_m
        scaled = pr.logits / max(self.temperature, 1e-6)
        e = (scaled - torch.gather(scaled, -1, mode)).exp_()  # the mode is the maximum; -inf ids give 0
        total = e.sum(-1)
        p_left, p_right = torch.where(left, e, 0.0).sum(-1), torch.where(right, e, 0.0).sum(-1)
        if sides is not None:
            sides = sides.to(total.device).expand_as(total)
            p_left, p_right = torch.where(sides > 0, p_left, 0.0), torch.where(sides < 0, p_right, 0.0)
            left, right = left & (sides > 0)[..., None], right & (sides < 0)[..., None]
        side_p = torch.stack([p_right, total - p_left - p_right, p_left], -1) / total[..., None]  # 0 right, 1 kept, 2 left
        side_logp = side_p.clamp(min=0).log()  # a side without a valid token is -inf
        chosen = torch.multinomial(side_p.clamp(min=0).reshape(-1, 3), 1, generator=generator).reshape(side_p.shape[:-1])
        in_side = torch.where(chosen[..., None] == 2, left, torch.where(chosen[..., None] == 0, right, ~(left | right)))
        token = pr.logits.masked_fill(~in_side, float("-inf")).argmax(-1)
        logp = torch.gather(side_logp, -1, chosen[..., None]).squeeze(-1)
        logp_full = torch.gather(pr.logp, -1, token[..., None]).squeeze(-1)
        return SampleOut(token, logp, pr.entropy, torch.isfinite(side_logp).sum(-1), logp_full)

    def draw(self, logits: torch.Tensor, generator: torch.Generator | None = None,
             token_lateral: torch.Tensor | None = None, sides: torch.Tensor | None = None,
             token_forward: torch.Tensor | None = None, token_forward_order: torch.Tensor | None = None,
             quantile: torch.Tensor | None = None) -> torch.Tensor:
        """Only the chosen tokens ``[...]`` (int64): the same draws as ``self(logits, generator).token``, without
        the full distribution's log-softmax and entropy where the rule does not need them (``greedy``, ``topk``:
        about a third of a 700-agent drop-in decision's sampling time over 3,720 tokens); other rules call
        :meth:`__call__`. Rows of NaN or all ``-inf`` logits fall back to token 0 with the same warning."""
        if self.kind not in ("greedy", "topk", "median"):
            return self(logits, generator, token_lateral, sides, token_forward, token_forward_order, quantile).token
        logits = logits.float()
        V = logits.shape[-1]
        if self.kind == "median":
            if token_forward is None:
                raise ValueError("sampler 'median' needs each token's forward travel (token_forward_m(vocab, agent_type))")
            top_vals, _ = max_blocked(logits)
            bad = ~torch.isfinite(top_vals[..., 0])  # a NaN or no finite id in the row: token 0, as the others
            if bool(bad.any()):
                _warn_fallback(bad, stacklevel=3)
                only0 = torch.full_like(logits, float("-inf"))
                only0[..., 0] = 0.0
                logits = torch.where(bad[..., None], only0, logits)
            return _median_token(logits, token_forward, token_forward_order, self.forward_m, self.temperature,
                                 quantile=self.quantile if quantile is None else quantile)
        if self.kind == "greedy":
            top_vals, top_idx = max_blocked(logits)
        else:
            top_vals, top_idx = topk_sorted(logits, min(self.k, V))  # [..., k], NaN sorts first
        bad = ~torch.isfinite(top_vals[..., 0])  # NaN anywhere in a row ranks first (topk, max), all -inf: -inf
        if bool(bad.any()):
            _warn_fallback(bad, stacklevel=3)
            keep = torch.zeros_like(top_vals)
            keep[..., 1:] = float("-inf")
            top_vals = torch.where(bad[..., None], keep, top_vals)
            top_idx = torch.where(bad[..., None], torch.zeros_like(top_idx), top_idx)
        if self.kind == "greedy":
            return top_idx[..., 0]
        k = torch.full(top_vals.shape[:-1], top_vals.shape[-1], dtype=torch.long, device=logits.device)
        return _draw_from_top(top_vals, top_idx, k, self.temperature, generator)[0]

    @property
    def spec(self) -> str:
        base = {
            "greedy": "greedy",
            "topk": f"topk:{self.k}",
            "entropy": f"entropy:{self.k_min},{self.k_max}",
            "entropy-norm": f"entropy-norm:{self.k_min},{self.k_max}",
            "full": "full",
            "intent": f"intent:{self.lateral_m:g}",
            "median": f"median:{self.forward_m:g}" if self.quantile == 0.5 else f"quantile:{self.quantile:g},{self.forward_m:g}",
        }[self.kind]
        return base if self.temperature == 1.0 else f"{base}@{self.temperature:g}"


def parse_sampler(spec: str) -> Sampler:
    """Parse ``greedy | full | topk:K | entropy:KMIN,KMAX | entropy-norm:KMIN,KMAX | intent:METRES | median:METRES |
    quantile:Q,METRES`` with optional ``@TEMP`` (``quantile:0.5,D`` is ``median:D``)."""
    s = spec.strip()
    temp = 1.0
    if "@" in s:
        s, t = s.split("@", 1)
        try:
            temp = float(t)
        except ValueError:
            raise ValueError(f"sampler '{spec}': temperature '{t}' is not a number") from None
        if not temp > 0:
            raise ValueError(f"sampler '{spec}': temperature must be > 0")
    kind, _, arg = s.partition(":")
    try:
        if kind in ("greedy", "full") and not arg:
            return Sampler(kind=kind, temperature=temp)
        if kind == "topk":
            k = int(arg)
            if k < 1:
                raise ValueError
            return Sampler(kind="topk", k=k, temperature=temp)
        if kind in ("entropy", "entropy-norm"):
            lo, hi = (int(v) for v in arg.split(","))
            if not 1 <= lo <= hi:
                raise ValueError
            return Sampler(kind=kind, k_min=lo, k_max=hi, temperature=temp)
        if kind == "intent":
            d = float(arg)
            if not d > 0:
                raise ValueError
            return Sampler(kind="intent", lateral_m=d, temperature=temp)
        if kind == "median":
            d = float(arg)
            if not d >= 0:
                raise ValueError
            return Sampler(kind="median", forward_m=d, temperature=temp)
        if kind == "quantile":
            q_s, d_s = arg.split(",")
            q, d = float(q_s), float(d_s)
            if not (0.0 < q < 1.0 and d >= 0):
                raise ValueError
            return Sampler(kind="median", forward_m=d, quantile=q, temperature=temp)
    except ValueError:
        pass
    raise ValueError(f"sampler '{spec}' not understood; use greedy, full, topk:32, entropy:16,80, entropy-norm:16,80, intent:0.25, median:0.1 or quantile:0.6,0.1 (Q in (0, 1), optionally @TEMP)")


def min_paper_k(k_min: int, k_max: int) -> float:
    """The smallest K_t the paper's formula can give (H_t = 0): (k_min + k_max) / 2."""
    return k_min + (k_max - k_min) / (1 + math.exp(0.0))
