"""Token samplers: greedy, fixed top-K, entropy-guided adaptive top-K (R1Sim), temperature.

Every sampler maps logits ``[..., V]`` (invalid ids already at ``-inf``) to a :class:`SampleOut` holding the
chosen token, the sampler's own log-probability of it (under the truncated, tempered distribution actually
sampled from — GRPO's "old" log-prob), the Shannon entropy ``H_t`` [nats] of the full model distribution and the
``K_t`` used.

Entropy-guided adaptive top-K (paper, Eq. K_t): ``K_t = k_min + (k_max - k_min) / (1 + exp(-H_t))``. Because
``H_t >= 0`` the sigmoid is >= 0.5, so as written ``K_t`` never drops below ``(k_min + k_max) / 2``; the
``normalised`` variant uses ``K_t = k_min + (k_max - k_min) * H_t / log(V)`` which spans the whole range.
Spec strings (CLI/config): ``greedy``, ``topk:32``, ``entropy:16,80``, ``entropy-norm:16,80``, with an optional
``@T`` temperature suffix (``topk:32@0.8``).
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


def entropy_of(logits: torch.Tensor) -> torch.Tensor:
    """Shannon entropy [nats] of softmax(logits) over the last dim; ``-inf`` entries contribute 0."""
    logp = torch.log_softmax(logits.float(), dim=-1)
    p = logp.exp()
    return -(p * torch.where(torch.isfinite(logp), logp, torch.zeros_like(logp))).sum(-1)


def _sanitize(logits: torch.Tensor) -> torch.Tensor:
    """Guard against NaN rows / all -inf rows: such rows fall back to token 0 (standing still)."""
    logits = logits.float()
    bad = torch.isnan(logits).any(-1, keepdim=True) | ~torch.isfinite(logits).any(-1, keepdim=True)
    if bad.any():
        fallback = torch.full_like(logits, float("-inf"))
        fallback[..., 0] = 0.0
        logits = torch.where(bad, fallback, torch.nan_to_num(logits, nan=float("-inf")))
    return logits


def sample_topk_per_row(logits: torch.Tensor, k: torch.Tensor, temperature: float = 1.0, generator: torch.Generator | None = None) -> SampleOut:
    """Sample from the top-``k`` logits of each row, ``k`` an int64 tensor broadcastable to ``logits[..., 0]``."""
    logits = _sanitize(logits)
    V = logits.shape[-1]
    n_valid = torch.isfinite(logits).sum(-1)  # [...]
    k = torch.minimum(torch.as_tensor(k, device=logits.device).expand_as(n_valid).clamp(min=1), n_valid.clamp(min=1))
    kmax = int(k.max()) if k.numel() else 1
    top_vals, top_idx = torch.topk(logits, min(kmax, V), dim=-1)  # [..., kmax]
    rank = torch.arange(top_vals.shape[-1], device=logits.device)
    keep = rank < k[..., None]
    scaled = torch.where(keep, top_vals / max(temperature, 1e-6), torch.full_like(top_vals, float("-inf")))
    logp_trunc = torch.log_softmax(scaled, dim=-1)
    flat = logp_trunc.reshape(-1, logp_trunc.shape[-1]).exp()
    choice = torch.multinomial(flat, 1, generator=generator).reshape(k.shape)  # [...]
    token = torch.gather(top_idx, -1, choice[..., None]).squeeze(-1)
    logp = torch.gather(logp_trunc, -1, choice[..., None]).squeeze(-1)
    return SampleOut(token, logp, entropy_of(logits), k)


@dataclass(frozen=True)
class Sampler:
    """A token-sampling rule. ``kind`` in {"greedy", "topk", "entropy", "entropy-norm", "full"}."""

    kind: str = "entropy"
    k: int = 32  # fixed top-K
    k_min: int = 16  # entropy-guided lower bound
    k_max: int = 80  # entropy-guided upper bound
    temperature: float = 1.0

    def choose_k(self, logits: torch.Tensor, entropy: torch.Tensor) -> torch.Tensor:
        n_valid = torch.isfinite(logits).sum(-1)
        if self.kind == "topk":
            return torch.full_like(n_valid, self.k)
        if self.kind == "entropy":
            kf = self.k_min + (self.k_max - self.k_min) * torch.sigmoid(entropy)
            return kf.round().long()
        if self.kind == "entropy-norm":
            h_norm = entropy / torch.log(n_valid.clamp(min=2).float())
            return (self.k_min + (self.k_max - self.k_min) * h_norm.clamp(0, 1)).round().long()
        if self.kind == "full":
            return n_valid
        raise ValueError(f"unknown sampler kind '{self.kind}'")

    def __call__(self, logits: torch.Tensor, generator: torch.Generator | None = None) -> SampleOut:
        if self.kind == "greedy":
            logits = _sanitize(logits)
            logp = torch.log_softmax(logits, -1)
            token = logits.argmax(-1)
            ones = torch.ones_like(token)
            return SampleOut(token, torch.zeros_like(logp[..., 0]), entropy_of(logits), ones)
        ent = entropy_of(_sanitize(logits))
        return sample_topk_per_row(logits, self.choose_k(logits, ent), self.temperature, generator)

    @property
    def spec(self) -> str:
        base = {
            "greedy": "greedy",
            "topk": f"topk:{self.k}",
            "entropy": f"entropy:{self.k_min},{self.k_max}",
            "entropy-norm": f"entropy-norm:{self.k_min},{self.k_max}",
            "full": "full",
        }[self.kind]
        return base if self.temperature == 1.0 else f"{base}@{self.temperature:g}"


def parse_sampler(spec: str) -> Sampler:
    """Parse ``greedy | full | topk:K | entropy:KMIN,KMAX | entropy-norm:KMIN,KMAX`` with optional ``@TEMP``."""
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
    except ValueError:
        pass
    raise ValueError(f"sampler '{spec}' not understood; use greedy, full, topk:32, entropy:16,80 or entropy-norm:16,80 (optionally @TEMP)")


def min_paper_k(k_min: int, k_max: int) -> float:
    """The smallest K_t the paper's formula can give (H_t = 0): (k_min + k_max) / 2."""
    return k_min + (k_max - k_min) / (1 + math.exp(0.0))
