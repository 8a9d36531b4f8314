"""Next-token baselines the policy must beat on held-out data: unigram and constant-velocity tokens.

Both are scored like the policy: top-1 accuracy and NLL [nats] of the matched ground-truth token over the
valid *future* tokens (steps 2..17) of tokenized scenes.

- **Unigram**: per agent type, the token frequencies of the training split (add-one smoothing); top-1 = the
  most frequent token.
- **Constant velocity (CV)**: at step k, the previous matched token k-1 gives the agent's speed at its end
  (last frame displacement / 0.1 s); the CV prediction is the straight continuation at that speed for 0.5 s.
  The distribution is ``softmax(-d / tau)`` over the vocabulary, with ``d`` the mean end-frame corner distance
  [m] of each token to that continuation and ``tau`` [m] fitted on the training split by a grid search.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from r1sim_sumo.scenario import DT_S
from r1sim_sumo.tokens.motion_vocab import TYPES, MotionVocab

FUTURE = slice(2, 18)


def _future_pairs(scenes: Iterable) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stack (agent_type, previous token, target token) over valid future steps with a valid previous token."""
    types, prevs, tgts = [], [], []
    for sc in scenes:
        a = sc.agents
        tok, tv = np.asarray(a.token), np.asarray(a.token_valid, bool)
        prev, pv = tok[:, 1:17], tv[:, 1:17]
        tgt, gv = tok[:, FUTURE], tv[:, FUTURE]
        m = gv & pv
        types.append(np.broadcast_to(np.asarray(a.agent_type)[:, None], m.shape)[m])
        prevs.append(prev[m])
        tgts.append(tgt[m])
    if not types:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(types).astype(np.int64), np.concatenate(prevs).astype(np.int64), np.concatenate(tgts).astype(np.int64)


class UnigramBaseline:
    def __init__(self, vocab: MotionVocab):
        self.vocab = vocab
        self.counts = {t: np.ones(vocab.size(t), np.float64) for t in TYPES}

    def fit(self, scenes: Iterable) -> UnigramBaseline:
        ty, _, tgt = _future_pairs(scenes)
        for t in TYPES:
            np.add.at(self.counts[t], tgt[ty == t], 1.0)
        return self

    def score(self, scenes: Iterable) -> dict:
        ty, _, tgt = _future_pairs(scenes)
        nll, ok = 0.0, 0
        for t in TYPES:
            m = ty == t
            if not m.any():
                continue
            logp = np.log(self.counts[t] / self.counts[t].sum())
            nll += float(-logp[tgt[m]].sum())
            ok += int((tgt[m] == int(np.argmax(self.counts[t]))).sum())
        n = len(tgt)
        return {"nll": nll / max(n, 1), "top1": ok / max(n, 1), "tokens": n}


class ConstantVelocityBaseline:
    def __init__(self, vocab: MotionVocab, tau_m: float = 0.5):
        self.vocab, self.tau_m = vocab, tau_m
        # per type: distance table [V_prev, V] between each token and the CV continuation of each previous token
        self._dist = {t: self._cv_distance(t) for t in TYPES}

    def _cv_distance(self, t: int) -> np.ndarray:
        traj, corners = self.vocab.traj[t], self.vocab.corners[t]  # [V, 6, 3], [V, 6, 4, 2]
        v_end = np.linalg.norm(traj[:, 5, :2] - traj[:, 4, :2], axis=-1) / DT_S  # [V] speed at the end [m/s]
        # corners at the end of a straight 0.5 s move at v_end, in the new start frame (heading 0)
        end_c = corners[0, 0][None] + np.stack([v_end * 5 * DT_S, np.zeros_like(v_end)], -1)[:, None, :]  # [V, 4, 2]
        tok_end = corners[:, 5]  # [V, 4, 2]
        return np.linalg.norm(end_c[:, None] - tok_end[None], axis=-1).mean(-1).astype(np.float32)  # [V_prev, V]

    def _logp(self, t: int, prev: np.ndarray, tau: float) -> np.ndarray:
        z = -self._dist[t][prev] / tau  # [N, V]
        z -= z.max(-1, keepdims=True)
        return z - np.log(np.exp(z).sum(-1, keepdims=True))

    def _nll(self, ty, prev, tgt, tau) -> float:
        tot = 0.0
        for t in TYPES:
            m = ty == t
            if m.any():
                lp = self._logp(t, prev[m], tau)
                tot += float(-lp[np.arange(m.sum()), tgt[m]].sum())
        return tot

    def fit(self, scenes: Iterable, grid: Iterable[float] = (0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)) -> ConstantVelocityBaseline:
        ty, prev, tgt = _future_pairs(scenes)
        if len(tgt) > 50_000:
            sel = np.random.default_rng(0).choice(len(tgt), 50_000, replace=False)
            ty, prev, tgt = ty[sel], prev[sel], tgt[sel]
        best = min(grid, key=lambda tau: self._nll(ty, prev, tgt, tau))
        self.tau_m = float(best)
        return self

    def score(self, scenes: Iterable) -> dict:
        ty, prev, tgt = _future_pairs(scenes)
        ok = 0
        for t in TYPES:
            m = ty == t
            if m.any():
                ok += int((self._dist[t][prev[m]].argmin(-1) == tgt[m]).sum())
        n = len(tgt)
        return {"nll": self._nll(ty, prev, tgt, self.tau_m) / max(n, 1), "top1": ok / max(n, 1), "tokens": n, "tau_m": self.tau_m}
