"""The C kernel of :mod:`r1sim_sumo.model.gathered_attention` against the plain attention path: values and
gradients, gathered and per-edge (identity) sources, queries without neighbours, one and two threads, and the
packed training forward with the kernel on vs off."""

from __future__ import annotations

import pytest
import torch

from r1sim_sumo.model import gathered_attention as ga
from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.layers import EdgeAttention, RelAttentionBlock
from r1sim_sumo.model.packed import packed_loss
from r1sim_sumo.model.policy import TrafficPolicy
from r1sim_sumo.model.synthetic import synthetic_batch, synthetic_vocab

pytestmark = pytest.mark.skipif(not ga.available(), reason=f"kernel not built: {ga.unavailable_reason()}")


def _model():
    torch.manual_seed(0)
    cfg = PolicyConfig.preset("nano", agent_k=8, map_agent_k=8, map_k=8, dropout=0.0, agent_layers=2)
    voc = synthetic_vocab(cfg.vocab_sizes)
    return TrafficPolicy(cfg, voc), voc


def _inputs(N=300, Ns=200, E=8, Dc=16, Dr=12, H=4, identity=False, seed=0):
    g = torch.Generator().manual_seed(seed)
    src = torch.randn(N * E if identity else Ns, Dc, generator=g, requires_grad=True)
    idx = None if identity else torch.randint(0, Ns, (N, E), generator=g)
    rel = torch.randn(N, E, Dr, generator=g, requires_grad=True)
    mask = torch.rand(N, E, generator=g) > 0.3
    mask[:7] = False  # queries without any neighbour
    mask[7, 1:] = False  # a query with exactly one
    qe = torch.randn(H, N, Dc + Dr, generator=g, requires_grad=True)
    return qe, src, idx, rel, mask


def _plain(qe, src, idx, rel, mask):
    H, N, _ = qe.shape
    content = src.view(N, mask.shape[1], -1) if idx is None else src[idx]
    e = torch.cat([content, rel], -1)
    return EdgeAttention.apply(qe.transpose(0, 1), e, mask.view(N, 1, -1)).transpose(0, 1)


@pytest.mark.parametrize("identity", [False, True])
@pytest.mark.parametrize("threads", [1, 2])
def test_kernel_matches_plain_attention_values_and_gradients(identity, threads):
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        args = _inputs(identity=identity)
        g = torch.randn(args[0].shape, generator=torch.Generator().manual_seed(1))
        leaves = [args[0], args[1], args[3]]
        out_ref = _plain(*args)
        grads_ref = torch.autograd.grad(out_ref, leaves, g)
        out = ga.gathered_edge_attention(*args)
        grads = torch.autograd.grad(out, leaves, g)
    finally:
        torch.set_num_threads(prev)
    assert out.shape == out_ref.shape
    torch.testing.assert_close(out, out_ref, atol=1e-5, rtol=1e-4)
    assert float(out[:, :7].abs().max()) == 0.0  # no neighbour: zero output
    for a, b in zip(grads, grads_ref, strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)


def test_block_forward_gathered_equals_forward_with_materialised_edges(monkeypatch):
    torch.manual_seed(0)
    blk = RelAttentionBlock(dim=32, heads=4, edge_dim=64, ffn_mult=2, dropout=0.0)
    x = torch.randn(120, 32, requires_grad=True)
    idx = torch.randint(0, 120, (120, 6))
    rel = torch.randn(120, 6, 32, requires_grad=True)
    mask = torch.rand(120, 6) > 0.2
    xn = blk.normed(x)
    fused = blk.forward_gathered(x, xn, xn, idx, rel, mask)
    plain = blk(x, xn, torch.cat([xn[idx], rel], -1), mask)
    torch.testing.assert_close(fused, plain, atol=1e-5, rtol=1e-4)
    gf = torch.autograd.grad(fused.square().sum(), [x, rel, *blk.parameters()], retain_graph=True)
    gp = torch.autograd.grad(plain.square().sum(), [x, rel, *blk.parameters()])
    for a, b in zip(gf, gp, strict=True):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-3)
    monkeypatch.setenv("R1SIM_FUSED_ATTENTION", "0")  # the switch: the plain path, same values
    assert not ga.usable(x)
    torch.testing.assert_close(blk.forward_gathered(x, xn, xn, idx, rel, mask), plain, atol=1e-6, rtol=1e-6)


def test_packed_training_loss_and_gradients_equal_with_kernel_on_and_off(monkeypatch):
    model, voc = _model()
    batch = synthetic_batch(voc, num_scenes=3, num_agents=20, num_map_tokens=300, seed=2, vehicle_fraction=0.6)

    def run():
        model.zero_grad(set_to_none=True)
        loss, _ = packed_loss(model, batch, 0.1)
        loss.backward()
        return float(loss), [p.grad.clone() for p in model.parameters() if p.grad is not None]

    monkeypatch.setenv("R1SIM_FUSED_ATTENTION", "1")
    loss_k, grads_k = run()
    monkeypatch.setenv("R1SIM_FUSED_ATTENTION", "0")
    loss_p, grads_p = run()
    assert abs(loss_k - loss_p) < 1e-5
    assert len(grads_k) == len(grads_p) > 10
    for a, b in zip(grads_k, grads_p, strict=True):
        torch.testing.assert_close(a, b, atol=2e-5, rtol=1e-3)


def test_under_bf16_autocast_the_kernel_path_tracks_the_plain_path(monkeypatch):
    """bf16 autocast on a CPU: the attention core runs in fp32 in the kernel, the layers around it in bf16; the
    loss stays within bf16 rounding of the plain bf16 path."""
    model, voc = _model()
    batch = synthetic_batch(voc, num_scenes=2, num_agents=16, num_map_tokens=200, seed=3, vehicle_fraction=0.6)
    losses = {}
    for flag in ("1", "0"):
        monkeypatch.setenv("R1SIM_FUSED_ATTENTION", flag)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            loss, _ = packed_loss(model, batch, 0.1)
        loss.backward()
        assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
        model.zero_grad(set_to_none=True)
        losses[flag] = float(loss)
    assert abs(losses["1"] - losses["0"]) < 2e-2 * abs(losses["0"])


def test_without_a_working_compiler_the_kernel_is_off_and_training_still_runs(tmp_path):
    """A machine whose C compiler fails: ``available()`` is False with the compiler's reason, and the packed
    training forward runs on the plain path; the residual dropout falls back to ``F.dropout`` (a fresh process: the
    build result is cached per process)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    code = (
        "import torch\n"
        "from r1sim_sumo.model import gathered_attention as ga\n"
        "from tests.test_gathered_attention import _model, synthetic_batch, packed_loss\n"
        "assert not ga.available() and 'could not build' in ga.unavailable_reason(), ga.unavailable_reason()\n"
        "m, voc = _model()\n"
        "loss, _ = packed_loss(m, synthetic_batch(voc, num_scenes=2, num_agents=8, num_map_tokens=100, seed=1))\n"
        "loss.backward()\n"
        "from r1sim_sumo.model import residual_dropout as rd\n"  # the dropout kernel falls back the same way
        "assert not rd.KERNEL.available() and 'could not build' in rd.KERNEL.unavailable_reason()\n"
        "x, u = torch.randn(10, 4), torch.randn(10, 4)\n"
        "torch.manual_seed(0); y = rd.residual_dropout(x, u, 0.5, True)\n"
        "torch.manual_seed(0); assert torch.equal(y, x + torch.nn.functional.dropout(u, 0.5, True))\n"
        "print('ok', float(loss))\n"
    )
    env = dict(os.environ, CC="false", R1SIM_KERNEL_CACHE=str(tmp_path / "kernels"), PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("ok")
    assert not any((tmp_path / "kernels").glob("*.so"))


def test_bf16_queries_give_the_fp32_result_within_bf16_rounding():
    """bf16 ``qe`` (what bf16 autocast's batched product gives): output and gradients in bf16, computed in fp32 from
    the bf16 inputs, so they match the fp32 kernel on the same (rounded) inputs to bf16 precision."""
    qe, src, idx, rel, mask = _inputs()
    qb = qe.detach().bfloat16().requires_grad_()
    q32 = qb.detach().float().requires_grad_()  # the same values in fp32
    g = torch.randn(qe.shape, generator=torch.Generator().manual_seed(2)).bfloat16()
    out_b = ga.gathered_edge_attention(qb, src, idx, rel, mask)
    out_f = ga.gathered_edge_attention(q32, src, idx, rel, mask)
    assert out_b.dtype == torch.bfloat16 and out_f.dtype == torch.float32
    torch.testing.assert_close(out_b.float(), out_f, atol=2e-2, rtol=1e-2)
    gb = torch.autograd.grad(out_b, [qb, src, rel], g)
    gf = torch.autograd.grad(out_f, [q32, src, rel], g.float())
    assert gb[0].dtype == torch.bfloat16 and gb[1].dtype == torch.float32
    for a, b in zip(gb, gf, strict=True):
        torch.testing.assert_close(a.float(), b, atol=3e-2, rtol=2e-2)


@pytest.mark.parametrize("identity", [False, True])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("which", ["src", "rel", "both"])
def test_bf16_edge_features_are_read_and_their_gradients_written_without_a_cast(identity, threads, which):
    """bf16 ``src`` / ``rel`` (the linear layers' outputs under autocast) go into the kernel as they are: the result
    equals the fp32 kernel on the same rounded values (arithmetic is fp32 either way), and each gradient comes back
    in its input's dtype, equal to the fp32 gradient rounded once to bf16 (a scatter sums in fp32 first), within one
    bf16 step (float sums in another order may round to the neighbouring bf16 value)."""
    qe, src, idx, rel, mask = _inputs(identity=identity)
    to_bf = {"src": which in ("src", "both"), "rel": which in ("rel", "both")}
    sb = src.detach().bfloat16() if to_bf["src"] else src.detach()
    rb = rel.detach().bfloat16() if to_bf["rel"] else rel.detach()
    lo = [qe.detach().clone().requires_grad_(), sb.clone().requires_grad_(), rb.clone().requires_grad_()]
    hi = [qe.detach().clone().requires_grad_(), sb.float().requires_grad_(), rb.float().requires_grad_()]
    g = torch.randn(qe.shape, generator=torch.Generator().manual_seed(3))
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        out_lo = ga.gathered_edge_attention(lo[0], lo[1], idx, lo[2], mask)
        out_hi = ga.gathered_edge_attention(hi[0], hi[1], idx, hi[2], mask)
        g_lo = torch.autograd.grad(out_lo, lo, g)
        g_hi = torch.autograd.grad(out_hi, hi, g)
    finally:
        torch.set_num_threads(prev)
    torch.testing.assert_close(out_lo, out_hi, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(g_lo[0], g_hi[0], atol=1e-5, rtol=1e-5)
    for a, b, name in ((g_lo[1], g_hi[1], "src"), (g_lo[2], g_hi[2], "rel")):
        assert a.dtype == (torch.bfloat16 if to_bf[name] else torch.float32), name
        torch.testing.assert_close(a.float(), b.to(a.dtype).float(), atol=1e-5, rtol=2**-7), name  # <= 1 bf16 step
