"""TALO math (common/algos/talo.py) against finite differences and the paper's conditions."""
from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from common.algos.talo import (
    cosine,
    equal_length_ab,
    individual_gradient,
    talo_direction,
    talo_gap,
    talo_project,
    unflatten_like,
)

F64 = torch.float64  # finite differences need double precision


def coupled_model(seed: int = 0, n: int = 3, dim: int = 4):
    """Three parameter blocks with coupled smooth surrogates.

    L_i depends on every block (like the SAIL-coupled surrogates) and the team
    surrogate is a different smooth function, so g_ind != g_team and the
    cross-block second derivatives are non-zero.
    """
    gen = torch.Generator().manual_seed(seed)
    thetas = [torch.randn(dim, generator=gen, dtype=F64).requires_grad_() for _ in range(n)]
    A = [torch.randn(dim, dim * n, generator=gen, dtype=F64) * 0.5 for _ in range(n)]
    x = torch.randn(16, dim, generator=gen, dtype=F64)
    adv = torch.randn(16, generator=gen, dtype=F64)

    def surrogates(ths):
        full = torch.cat(ths)
        # per-carrier "log-ratio" of a coupled center, like SAIL's output
        logr = [x @ torch.tanh(A[i] @ full) * 0.3 + 0.1 * (x @ ths[i]) for i in range(n)]
        L = [(torch.exp(lr) * adv).mean() for lr in logr]
        team = (torch.exp(torch.stack(logr).sum(0)) * adv).mean()
        return L, team

    return thetas, surrogates


def w_value(ths, surrogates) -> float:
    L, team = surrogates(ths)
    g_ind = individual_gradient(L, [[t] for t in ths])
    g_team = torch.autograd.grad(team, ths)
    g_team = torch.cat([g.reshape(-1) for g in g_team])
    return float(0.5 * (g_ind - g_team).pow(2).sum())


def test_grad_w_matches_central_finite_differences():
    thetas, surrogates = coupled_model()
    L, team = surrogates(thetas)
    _, _, w, grad_w = talo_gap(L, team, [[t] for t in thetas])
    assert float(w) > 1e-3  # the test is meaningless if the gap vanishes
    h = 1e-6
    fd = []
    for i, t in enumerate(thetas):
        for k in range(t.numel()):
            plus = [s.detach().clone().requires_grad_() for s in thetas]
            minus = [s.detach().clone().requires_grad_() for s in thetas]
            with torch.no_grad():
                plus[i][k] += h
                minus[i][k] -= h
            fd.append((w_value(plus, surrogates) - w_value(minus, surrogates)) / (2 * h))
    np.testing.assert_allclose(grad_w.numpy(), np.array(fd), rtol=1e-6, atol=1e-8)


def test_individual_blocks_are_partials_of_their_own_surrogate():
    thetas, surrogates = coupled_model(seed=1)
    groups = [[t] for t in thetas]
    L, _ = surrogates(thetas)
    g = individual_gradient(L, groups)
    blocks = unflatten_like(g, thetas)
    for i, t in enumerate(thetas):
        (ref,) = torch.autograd.grad(L[i], t, retain_graph=True)
        torch.testing.assert_close(blocks[i], ref, rtol=0, atol=0)
    # Changing the other surrogates (even in a way that depends on theta_i)
    # must not change block i.
    L2 = [L[0], L[1] + 5.0 * thetas[0].pow(3).sum(), L[2] - thetas[0].sum() * thetas[2].sum()]
    blocks2 = unflatten_like(individual_gradient(L2, groups), thetas)
    torch.testing.assert_close(blocks2[0], blocks[0], rtol=0, atol=0)
    assert not torch.allclose(blocks2[2], blocks[2])


def test_detached_partners_give_the_same_blocks_and_separable_shortcut():
    """Detaching partner branches (the paper's recipe) and taking the partial on
    the shared graph give the same g_ind; with detached partners the one-pass
    ``separable`` shortcut is valid."""
    thetas, surrogates = coupled_model(seed=2)
    groups = [[t] for t in thetas]
    L, _ = surrogates(thetas)
    g_shared = individual_gradient(L, groups)
    L_det = []
    for i in range(3):
        ths = [t if j == i else t.detach() for j, t in enumerate(thetas)]
        L_det.append(surrogates(ths)[0][i])
    g_det = individual_gradient(L_det, groups, separable=True)
    torch.testing.assert_close(g_det, g_shared, rtol=1e-12, atol=1e-12)


def test_unregularized_correction_meets_descent_condition_on_model():
    thetas, surrogates = coupled_model(seed=3)
    L, team = surrogates(thetas)
    for sigma in (0.1, 1.0, 10.0):
        res = talo_direction(L, team, [[t] for t in thetas], sigma=sigma, eps=0.0)
        assert res.grad_w.norm() > 0
        assert float(res.grad_w @ res.g_talo) <= -sigma * res.w_gap + 1e-9 * max(1.0, res.w_gap)
    assert -1.0 <= res.cos_ind_team <= 1.0


finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False)


def correction_overflows(g, gw, delta) -> bool:
    """Is the exact correction g - delta grad W / ||grad W||^2 (in rationals) beyond float64?"""
    gw_sq = sum(Fraction(x) ** 2 for x in gw)
    exact = (Fraction(a) - Fraction(delta) * Fraction(x) / gw_sq for a, x in zip(g, gw))
    return max(abs(x) for x in exact) > Fraction(np.finfo(np.float64).max)


@settings(max_examples=100, deadline=None)
@example(g=np.zeros(7), gw=np.full(7, 3.3256951e-162), w=1.0, sigma=3.3256950988844715e-162)   # found 2026-12-06
@example(g=np.zeros(7), gw=np.r_[9.58033258e-270, np.zeros(6)], w=1.0, sigma=1.0)   # ||grad W||^2 underflows
@example(g=np.zeros(7), gw=np.full(7, 2.22507386e-313), w=1.0, sigma=1.0)   # the step overflows (2026-12-07)
@given(
    g=arrays(np.float64, 7, elements=finite),
    gw=arrays(np.float64, 7, elements=finite),
    w=st.floats(0, 100),
    sigma=st.floats(0, 50),
)
@pytest.mark.sweep
def test_projection_properties(g, gw, w, sigma):
    g_t, gw_t = torch.tensor(g, dtype=F64), torch.tensor(gw, dtype=F64)
    out, delta = talo_project(g_t, gw_t, w, sigma=sigma, eps=0.0)
    assert delta == pytest.approx(float(gw_t @ g_t) + sigma * w, abs=1e-9)
    if delta <= 0 or not bool(gw_t.any()):
        # no correction: returned exactly
        assert torch.equal(out, g_t)
    elif torch.equal(out, g_t) and correction_overflows(g, gw, delta):
        pass   # documented: a correction float64 cannot hold leaves g_ind unchanged
    else:
        # Eq. (talo_condition) holds (with equality) and the change is along grad W
        assert torch.isfinite(out).all()
        lhs = float(gw_t @ out)
        # |gw . x| <= sum|gw| max|x|, never 0 * inf where ||out|| overflows
        scale = 1 + abs(sigma * w) + float(gw_t.abs().sum()) * float(torch.maximum(g_t.abs(), out.abs()).max())
        assert lhs <= -sigma * w + 1e-7 * scale
        resid = out - g_t
        u = gw_t / gw_t.abs().max()   # scaled first: a tiny grad W squares to subnormals
        u = u / u.norm()
        cross = resid - (resid @ u) * u
        assert float(cross.norm()) <= 1e-9 * (1 + float(resid.norm()))
    # the regularized correction is never larger than the unregularized one
    out_eps, _ = talo_project(g_t, gw_t, w, sigma=sigma, eps=1e-3)
    assert float((out_eps - g_t).norm()) <= float((out - g_t).norm()) + 1e-12


def test_no_correction_when_condition_already_holds():
    g = torch.tensor([1.0, -2.0, 0.5], dtype=F64)
    gw = torch.tensor([-1.0, 1.0, 0.0], dtype=F64)  # gw.g = -3
    out, delta = talo_project(g, gw, 1.0, sigma=2.0, eps=1e-8)
    assert delta == pytest.approx(-1.0)
    assert torch.equal(out, g)


def test_talo_step_decreases_gap_to_first_order():
    thetas, surrogates = coupled_model(seed=4)
    L, team = surrogates(thetas)
    res = talo_direction(L, team, [[t] for t in thetas], sigma=1.0, eps=1e-8)
    assert res.corrected  # this seed has an uncorrected direction that grows W

    def w_after(direction, step):
        ths = [
            (t.detach() + step * d).requires_grad_()
            for t, d in zip(thetas, unflatten_like(direction, thetas))
        ]
        return w_value(ths, surrogates)

    step = 1e-5
    dw_talo = (w_after(res.g_talo, step) - res.w_gap) / step
    dw_ind = (w_after(res.g_ind, step) - res.w_gap) / step
    assert dw_talo < dw_ind
    assert dw_talo <= -1.0 * res.w_gap * 0.99  # descent condition, first order


def hand_model():
    """Two scalar blocks, L_1 = theta_1^2 / 2, L_2 = theta_2^2 / 2, L_team = theta_1 theta_2:
    g_ind = (theta_1, theta_2), g_team = (theta_2, theta_1), W_gap = (theta_1 - theta_2)^2."""
    def gap_at(theta):
        t1, t2 = (theta[0:1].clone().requires_grad_(), theta[1:2].clone().requires_grad_())
        L = [0.5 * t1.pow(2).sum(), 0.5 * t2.pow(2).sum()]
        return talo_gap(L, (t1 * t2).sum(), [[t1], [t2]])
    return gap_at


def test_equal_length_ab_agrees_with_a_hand_computation():
    """At theta = (1, 0), sigma = 1: W = 1, grad W = (2, -2), Delta = 2 + 1 = 3,
    g_TALO = (1, 0) - 3/8 (2, -2) = (1/4, 3/4). A step of length h along g_ind gives
    W = (1 + h)^2; along g_TALO (unit (1, 3)/sqrt(10)), W = (1 - 2h/sqrt(10))^2."""
    gap_at = hand_model()
    theta = torch.tensor([1.0, 0.0], dtype=F64)
    g_ind, g_team, w0, grad_w = gap_at(theta)
    torch.testing.assert_close(g_ind, torch.tensor([1.0, 0.0], dtype=F64))
    torch.testing.assert_close(g_team, torch.tensor([0.0, 1.0], dtype=F64))
    assert float(w0) == 1.0
    torch.testing.assert_close(grad_w, torch.tensor([2.0, -2.0], dtype=F64))
    g_talo, delta = talo_project(g_ind, grad_w, w0, sigma=1.0, eps=0.0)
    assert delta == 3.0
    torch.testing.assert_close(g_talo, torch.tensor([0.25, 0.75], dtype=F64))
    h = 0.5
    w_talo, w_ind = equal_length_ab(lambda d: float(gap_at(theta + d)[2]), float(w0), g_talo, g_ind, h)
    assert w_ind == pytest.approx((1 + h) ** 2, rel=1e-14)
    assert w_talo == pytest.approx((1 - 2 * h / 10 ** 0.5) ** 2, rel=1e-14)
    # no step, no direction, no correction
    assert equal_length_ab(lambda d: 99.0, 1.0, g_talo, g_ind, 0.0) == (1.0, 1.0)
    assert equal_length_ab(lambda d: 99.0, 1.0, torch.zeros(2, dtype=F64), g_ind, h) == (1.0, 99.0)
    calls = []
    assert equal_length_ab(lambda d: calls.append(d) or 7.0, 1.0, g_ind.clone(), g_ind, h) == (7.0, 7.0)
    assert len(calls) == 1
    with pytest.raises(ValueError):
        equal_length_ab(lambda d: 0.0, 1.0, g_talo, g_ind, -1.0)
    with pytest.raises(ValueError):
        equal_length_ab(lambda d: 0.0, 1.0, g_talo, g_ind, float("nan"))


def test_equal_length_ab_matches_the_first_order_rates_on_a_coupled_model():
    """Finite differences: for a short step h the A/B's two W_gap values move from W at
    the rates grad W . g / ||g|| of their directions (Eq. talo_condition's left side)."""
    thetas, surrogates = coupled_model(seed=4)
    L, team = surrogates(thetas)
    res = talo_direction(L, team, [[t] for t in thetas], sigma=1.0, eps=1e-8)
    assert res.corrected

    def w_at(displacement):
        return w_value([(t.detach() + d).requires_grad_()
                        for t, d in zip(thetas, unflatten_like(displacement, thetas))], surrogates)

    for h in (1e-4, 1e-5):
        w_talo, w_ind = equal_length_ab(w_at, res.w_gap, res.g_talo, res.g_ind, h)
        for w, g in ((w_talo, res.g_talo), (w_ind, res.g_ind)):
            rate = float(res.grad_w @ g / g.norm())
            assert (w - res.w_gap) / h == pytest.approx(rate, rel=50 * h, abs=1e-9)   # O(h) second-order term
        assert w_talo < w_ind


def test_cosine_and_errors():
    assert cosine(torch.tensor([1.0, 0.0]), torch.tensor([0.0, 2.0])) == pytest.approx(0.0)
    assert cosine(torch.tensor([1.0, 1.0]), torch.tensor([2.0, 2.0])) == pytest.approx(1.0)
    assert cosine(torch.zeros(2), torch.ones(2)) == 0.0
    with pytest.raises(ValueError):
        talo_project(torch.ones(2), torch.ones(2), 1.0, sigma=-1.0, eps=0.0)
    with pytest.raises(ValueError):
        individual_gradient([torch.tensor(1.0)], [[], []])
