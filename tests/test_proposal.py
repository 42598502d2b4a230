"""Squashed-Gaussian proposal: normalization, Monte Carlo agreement, torch/numpy twins, entropy."""
import math

import numpy as np
import pytest
import torch
from scipy import integrate, stats

from common.policy.proposal import (
    ProposalConfig,
    proposal_entropy,
    proposal_log_prob,
    proposal_log_prob_np,
    proposal_sample_np,
)


def _density_1d(center, log_std):
    return lambda x: math.exp(proposal_log_prob_np(np.full((1, 3), center), np.full(3, log_std), np.full((1, 3), x))[0, 0] / 3)


@pytest.mark.parametrize("center, log_std", [(0.0, -0.5), (0.7, 0.0), (-0.95, -1.5), (1.8, -0.5), (0.3, 0.8)])
def test_density_integrates_to_one(center, log_std):
    pdf = _density_1d(center, log_std)
    total, err = integrate.quad(pdf, -1.0, 1.0, points=[math.tanh(math.atanh(min(max(center, -0.999), 0.999)))], limit=200)
    assert abs(total - 1.0) < 1e-6, (total, err)


def test_log_prob_matches_closed_form_per_carrier():
    rng = np.random.default_rng(0)
    center, log_std = rng.uniform(-1.2, 1.2, (6, 9)), rng.uniform(-1, 0.5, 9)
    a = rng.uniform(-0.999, 0.999, (6, 9))
    mu = np.arctanh(np.clip(center, -1 + 1e-3, 1 - 1e-3))
    per_dim = stats.norm.logpdf(np.arctanh(a), mu, np.exp(log_std)) - np.log(1 - a**2)  # change of variables
    expected = per_dim.reshape(6, 3, 3).sum(-1)
    np.testing.assert_allclose(proposal_log_prob_np(center, log_std, a), expected, rtol=1e-10)


@pytest.mark.sweep
def test_samples_follow_the_density():
    """Histogram of 400k samples against the exact density (1-D marginal)."""
    rng = np.random.default_rng(1)
    center, log_std = np.array([[0.6, -0.2, 0.99]]), np.array([-0.3, 0.2, -1.0])
    a, logp = proposal_sample_np(np.repeat(center, 400_000, 0), log_std, rng)
    assert np.all(np.abs(a) < 1) and a.shape == (400_000, 3) and logp.shape == (400_000, 1)
    for k in range(3):
        hist, edges = np.histogram(a[:, k], bins=40, range=(-1, 1), density=True)
        pdf = [integrate.quad(lambda x: math.exp(_log_pdf_1d(x, center[0, k], log_std[k])), lo, hi)[0] / (hi - lo)
               for lo, hi in zip(edges[:-1], edges[1:])]
        np.testing.assert_allclose(hist, pdf, atol=0.02 + 0.03 * np.max(pdf))
    # the Monte Carlo mean of -log p is the entropy; compare with quadrature
    pdf0 = lambda x: math.exp(_log_pdf_1d(x, center[0, 0], log_std[0]))  # noqa: E731
    h_quad = integrate.quad(lambda x: -pdf0(x) * _log_pdf_1d(x, center[0, 0], log_std[0]), -1, 1, limit=200)[0]
    lp0 = stats.norm.logpdf(np.arctanh(a[:, 0]), np.arctanh(0.6), np.exp(-0.3)) - np.log1p(-a[:, 0] ** 2)
    assert abs(-lp0.mean() - h_quad) < 0.01


def _log_pdf_1d(x, center, log_std):
    mu = math.atanh(min(max(center, -1 + 1e-3), 1 - 1e-3))
    return stats.norm.logpdf(math.atanh(x), mu, math.exp(log_std)) - math.log(1 - x * x)


def test_sampler_logp_is_exact_at_stored_float32_values():
    rng = np.random.default_rng(2)
    center = rng.uniform(-1.5, 1.5, (1000, 9))
    log_std = np.full(9, 0.3)
    a, logp = proposal_sample_np(center, log_std, rng)
    assert np.array_equal(a, a.astype(np.float32).astype(np.float64))  # lossless float32 storage
    bound = np.float32(1 - 1e-6)
    assert np.all(np.abs(a) <= bound) and np.any(np.abs(a) > 0.999)
    np.testing.assert_array_equal(logp, proposal_log_prob_np(center, log_std, a.astype(np.float32)))
    lp_t = proposal_log_prob(torch.from_numpy(center).float(), torch.from_numpy(log_std).float(), torch.from_numpy(a).float())
    np.testing.assert_allclose(lp_t.numpy(), logp, rtol=1e-6, atol=1e-5)  # learner side, float32 inputs


def test_torch_matches_numpy_and_is_differentiable():
    rng = np.random.default_rng(3)
    center = torch.tensor(rng.uniform(-0.9, 0.9, (5, 9)), dtype=torch.float64, requires_grad=True)
    log_std = torch.tensor(rng.uniform(-1, 0, 9), dtype=torch.float64, requires_grad=True)
    a = torch.tensor(rng.uniform(-0.99, 0.99, (5, 9)))
    lp = proposal_log_prob(center, log_std, a)
    np.testing.assert_allclose(lp.detach().numpy(), proposal_log_prob_np(center.detach().numpy(), log_std.detach().numpy(), a.numpy()), rtol=1e-12)
    assert torch.autograd.gradcheck(lambda c, s: proposal_log_prob(c, s, a), (center, log_std))
    # outside-the-box center: clipped, so no gradient through that coordinate but log_std still gets one
    outside = torch.tensor([[1.5] + [0.0] * 8], dtype=torch.float64, requires_grad=True)
    proposal_log_prob(outside, log_std, a[:1]).sum().backward()
    assert outside.grad[0, 0] == 0 and outside.grad[0, 1] != 0


@pytest.mark.sweep
def test_entropy():
    log_std = torch.tensor([-0.5, 0.0, 0.3, -1.0, -1.0, -1.0, 0.1, 0.2, 0.3], dtype=torch.float64, requires_grad=True)
    h = proposal_entropy(log_std)
    expected = stats.norm(scale=np.exp(log_std.detach().numpy())).entropy().reshape(3, 3).sum(-1)
    np.testing.assert_allclose(h.detach().numpy(), expected, rtol=1e-12)
    h.sum().backward()
    assert torch.allclose(log_std.grad, torch.ones(9, dtype=torch.float64))
    # squashed-entropy estimate vs quadrature, 1-D per dim
    center = torch.tensor([[0.3, -0.8, 0.95, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5]], dtype=torch.float64)
    est = proposal_entropy(log_std.detach(), center, n_samples=50_000, generator=torch.Generator().manual_seed(0))
    quad = []
    for k in range(9):
        c, s = float(center[0, k]), float(log_std.detach()[k])
        quad.append(integrate.quad(lambda x: -math.exp(_log_pdf_1d(x, c, s)) * _log_pdf_1d(x, c, s), -1, 1, limit=200)[0])
    np.testing.assert_allclose(est[0].numpy(), np.reshape(quad, (3, 3)).sum(-1), atol=0.02)
    assert torch.all(est[0] < h.detach())  # the pre-tanh entropy is an upper bound


def test_bad_inputs():
    with pytest.raises(ValueError, match=r"\|a\| < 1"):
        proposal_log_prob_np(np.zeros((1, 9)), np.zeros(9), np.ones((1, 9)))
    with pytest.raises(ValueError, match=r"\|a\| < 1"):
        proposal_log_prob(torch.zeros(1, 9), torch.zeros(9), torch.full((1, 9), float("nan")))
    with pytest.raises(ValueError, match="log_std"):
        proposal_sample_np(np.zeros((2, 9)), np.zeros(8), np.random.default_rng(0))
    with pytest.raises(ValueError, match="multiple"):
        proposal_log_prob_np(np.zeros((1, 8)), np.zeros(8), np.zeros((1, 8)))
    with pytest.raises(ValueError, match="finite"):
        proposal_sample_np(np.full((1, 9), np.inf), np.zeros(9), np.random.default_rng(0))
    assert ProposalConfig().act_dim == 3
