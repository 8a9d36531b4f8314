"""The hashed residual dropout of :mod:`r1sim_sumo.model.residual_dropout`: what it keeps, how often, its gradient,
its determinism under a seed, and the plain fallback."""

import pytest
import torch
import torch.nn.functional as F

from r1sim_sumo.model import residual_dropout as rd

pytestmark = pytest.mark.skipif(not rd.KERNEL.available(), reason=f"kernel not built: {rd.KERNEL.unavailable_reason()}")


def _xu(n=(300, 67), dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, generator=g).requires_grad_()
    u = (torch.rand(n, generator=g) + 1.0).to(dtype).requires_grad_()  # in [1, 2): kept / dropped is visible
    return x, u


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("threads", [1, 2])
def test_each_element_is_x_or_x_plus_scaled_u_and_the_gradient_follows_the_same_mask(dtype, threads):
    x, u = _xu(dtype=dtype)
    p = 0.1
    thr, scale = rd.threshold(p)
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        torch.manual_seed(5)
        y = rd.residual_dropout(x, u, p, training=True)
        g = torch.randn(y.shape)
        gx, gu = torch.autograd.grad(y, [x, u], g)
    finally:
        torch.set_num_threads(prev)
    assert y.dtype == torch.float32 and gu.dtype == dtype
    kept = (y - x).detach().abs() > 0.5  # kept: |u * scale| >= 1; dropped elements give exactly x
    torch.testing.assert_close(y[kept], (x + u.float() * scale)[kept], atol=1e-5, rtol=1e-5)
    assert torch.equal(y[~kept], x[~kept])
    frac = 1.0 - kept.float().mean().item()
    assert abs(frac - thr / 65536) < 0.01, frac  # 20,100 elements: 3 sigma ~ 0.006
    assert torch.equal(gx, g)
    torch.testing.assert_close(gu.float(), torch.where(kept, g * scale, 0.0).to(dtype).float(), atol=1e-6, rtol=0)


def test_masks_repeat_under_a_seed_differ_across_calls_and_do_not_depend_on_threads():
    x, u = _xu()
    ys = []
    for threads in (1, 2):
        prev = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            torch.manual_seed(7)
            ys.append((rd.residual_dropout(x, u, 0.3, True), rd.residual_dropout(x, u, 0.3, True)))
        finally:
            torch.set_num_threads(prev)
    assert torch.equal(ys[0][0], ys[1][0]) and torch.equal(ys[0][1], ys[1][1])
    assert not torch.equal(ys[0][0], ys[0][1])


def test_eval_and_p_zero_are_a_plain_add_and_the_switch_falls_back_to_f_dropout(monkeypatch):
    x, u = _xu()
    assert torch.equal(rd.residual_dropout(x, u, 0.1, training=False), x + u)
    assert torch.equal(rd.residual_dropout(x, u, 0.0, training=True), x + u)
    monkeypatch.setenv("R1SIM_FUSED_DROPOUT", "0")
    torch.manual_seed(3)
    y = rd.residual_dropout(x, u, 0.5, True)
    torch.manual_seed(3)
    assert torch.equal(y, x + F.dropout(u, 0.5, True))


def test_threshold_rounds_p_to_sixteen_bits_and_keeps_the_expectation():
    thr, scale = rd.threshold(0.1)
    assert thr == 6554 and abs(scale * (1 - thr / 65536) - 1.0) < 1e-12
    assert rd.threshold(0.0) == (0, 1.0)
