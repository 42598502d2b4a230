"""The learner's cheaper formulations against the ones they replaced: the
one-graph W_gap / HVP of ``talo_gap`` (d = g_ind - g_team taken directly as the
gradient of L_i - L_team) against g_ind and g_team each with
``create_graph=True`` and the double backward of 1/2 ||g_ind - g_team||^2 through
both; the coupled blocks taken through a_ST (``Through``) against one backward
per carrier; the HAPPO step reusing the diagnostics' g_ind and its SAIL solves against
recomputing them."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from common.algos import AlgoConfig, make_method
from common.algos.diagnostics import gap_diagnostics
from common.algos.sequential import happo_step
from common.algos.synthetic import BanditTask, collect
from common.algos.talo import Through, flat_grad, individual_gradient, talo_gap

F64 = torch.float64

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def two_graph_gap(losses, team, groups, separable):
    """The former ``talo_gap``: both gradient graphs kept, HVP through both."""
    params = [p for g in groups for p in g]
    g_ind = individual_gradient(losses, groups, create_graph=True, separable=separable)
    g_team = flat_grad(team, params, create_graph=True)
    w = 0.5 * (g_ind - g_team).pow(2).sum()
    return g_ind.detach(), g_team.detach(), w.detach(), flat_grad(w, params)


def random_model(seed: int, coupled: bool, n: int = 3, dim: int = 5):
    """Smooth PPO-like surrogates on random inputs; ``coupled``: L_i depends on
    every block (like SAIL), else on theta_i only (identity center)."""
    gen = torch.Generator().manual_seed(seed)
    thetas = [torch.randn(dim, generator=gen, dtype=F64).requires_grad_() for _ in range(n)]
    A = [torch.randn(dim, dim * n, generator=gen, dtype=F64) * 0.5 for _ in range(n)]
    x = torch.randn(32, dim, generator=gen, dtype=F64)
    adv = torch.randn(32, generator=gen, dtype=F64)
    full = torch.cat(thetas)
    logr = [0.3 * x @ torch.tanh(A[i] @ full if coupled else A[i][:, i * dim:(i + 1) * dim] @ thetas[i])
            + 0.1 * x @ thetas[i] for i in range(n)]

    def clip(r):
        return torch.minimum(r * adv, r.clamp(0.8, 1.2) * adv).mean()

    L = [clip(lr.exp()) for lr in logr]
    team = clip(torch.stack(logr).sum(0).exp())
    return [[t] for t in thetas], L, team


def prepared_double(name: str, seed: int = 1, obs: int = 6):
    m = make_method(name, AlgoConfig(), obs, 0)
    task = BanditTask(obs_dim=obs, seed=seed, n_rows=10, row_frac=0.5, human_rate=0.2)
    batch = collect(m, task, 6, 8, 0.5, np.random.default_rng(seed))
    m.policy.double()
    m.proposal.closed_form = False     # these tests are about talo_gap on the autograd graph
    mb, _ = m._prepare(batch)
    return m, mb


def flat(m):
    return torch.cat([p.detach().reshape(-1) for p in m.actor_params])


def assert_same(new, old, rtol=1e-10, atol=1e-12):
    for a, b in zip(new, old):
        torch.testing.assert_close(torch.as_tensor(a), torch.as_tensor(b), rtol=rtol, atol=atol)


@pytest.mark.parametrize("coupled", [True, False])
@pytest.mark.parametrize("seed", range(5))
def test_one_graph_gap_equals_two_graph_gap_on_random_models(seed, coupled):
    groups, L, team = random_model(seed, coupled)
    new = talo_gap(L, team, groups, separable=not coupled)
    old = two_graph_gap(L, team, groups, separable=not coupled)
    assert float(old[2]) > 1e-6 and float(old[3].norm()) > 1e-6
    assert_same(new, old)
    # the diagnostics path (no HVP) gives the same g_ind, g_team and W_gap
    assert_same(talo_gap(L, team, groups, separable=not coupled, with_hvp=False)[:3], old[:3])


@pytest.mark.parametrize("name", ["sage", "talo_cbf"])
def test_one_graph_gap_equals_two_graph_gap_on_the_learner(name):
    """The learner's own surrogates (hard trees, SAIL center or identity, human
    blocks) in double precision, off-policy so that W_gap > 0 for both."""
    m, mb = prepared_double(name)
    with torch.no_grad():   # off-policy start point
        for p in m.actor_params:
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel()), dtype=F64))
    _, _, behaviour, _ = m.proposal.start_point(mb, 0.5, 3.0)
    L, team = behaviour.L_ind, behaviour.L_team
    new = talo_gap(L, team, m.groups, separable=not m.uses_sail)
    old = two_graph_gap(L, team, m.groups, separable=not m.uses_sail)
    assert float(old[2]) > 1e-8
    assert_same(new, old, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("with_hvp", [True, False])
@pytest.mark.parametrize("name", ["sage", "sail_cbf"])
def test_coupled_blocks_through_a_st_equal_one_backward_per_carrier(name, with_hvp):
    """SAIL couples the carriers, so block i of d = g_ind - g_team is grad_{theta_i}
    (L_i - L_team) with every L_j depending on every tree. Taken through the trees'
    stacked actions (one backward per carrier down to a_ST, one vector-Jacobian product
    through all trees) it must give the same g_ind, g_team, W_gap and HVP."""
    m, mb = prepared_double(name)
    with torch.no_grad():   # off-policy start point: W_gap > 0
        for p in m.actor_params:
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel()), dtype=F64))
    a_st, _, behaviour, _ = m.proposal.start_point(mb, 0.5, 3.0)
    L, team = behaviour.L_ind, behaviour.L_team
    new = talo_gap(L, team, m.groups, with_hvp=with_hvp, through=m.proposal.through(a_st))
    old = talo_gap(L, team, m.groups, with_hvp=with_hvp)
    assert float(old[2]) > 1e-8 and old[0].abs().min() < old[0].abs().max()
    assert_same(new if with_hvp else new[:3], old if with_hvp else old[:3], rtol=1e-9, atol=1e-12)
    # the log_std blocks come from the direct route, the tree blocks from the product through a_ST
    sizes = [p.numel() for p in m.actor_params]
    log_std_entries = torch.cat([b for b, p in zip(new[0].split(sizes), m.actor_params)
                                 if any(p is t.log_std for t in m.trees)])
    assert log_std_entries.abs().max() > 0


def test_through_rejects_slices_that_do_not_tile_the_intermediate():
    m, mb = prepared_double("sage")
    a_st, _, behaviour, _ = m.proposal.start_point(mb, 0.5, 3.0)
    L, team = behaviour.L_ind, behaviour.L_team
    via = [[t.W, t.b, t.K, t.beta] for t in m.trees]
    for slices in ([slice(0, 3), slice(3, 6), slice(6, 8)], [slice(0, 3), slice(6, 9), slice(3, 6)]):
        with pytest.raises(ValueError, match="tile"):
            talo_gap(L, team, m.groups, through=Through(a_st, slices, via))
    with pytest.raises(ValueError, match="graph"):
        talo_gap(L, team, m.groups, through=Through(a_st.detach(), m.proposal.through(a_st).slices, via))


@pytest.mark.parametrize("name", ["happo", "sail_cbf"])
def test_happo_step_reusing_the_diagnostics_gradient_is_the_plain_step(name):
    """The first carrier's HAPPO gradient (M = 1) taken from the diagnostics' g_ind
    gives the same step, factors and statistics as recomputing it."""
    (a, mb), (b, _) = prepared_double(name), prepared_double(name)
    order = [2, 0, 1]
    _, start = gap_diagnostics(a.proposal, mb, 0.5, 3.0)
    sa = happo_step(a, mb, 0.5, 3.0, order=order, start=start)
    sb = happo_step(b, mb, 0.5, 3.0, order=order)
    assert not torch.equal(flat(a), flat(prepared_double(name)[0]))   # a step was taken
    torch.testing.assert_close(flat(a), flat(b), rtol=1e-9, atol=1e-12)
    for i in order:
        torch.testing.assert_close(a.last_happo_factors[i], b.last_happo_factors[i], rtol=1e-9, atol=1e-12)
    assert sa == pytest.approx(sb, rel=1e-9, abs=1e-12)


def test_sequential_sail_steps_are_reused_with_the_same_result(monkeypatch):
    """sail_cbf's HAPPO step builds each carrier's graph on the SAIL step its
    refresh solved (one solve per carrier after the first, none repeated): the same
    parameters, factors and statistics as solving every center afresh."""
    from common.algos import proposal_map

    calls = []
    counted = proposal_map.sail_step
    monkeypatch.setattr(proposal_map, "sail_step", lambda *a, **k: calls.append(1) or counted(*a, **k))
    (a, mb), (b, _) = prepared_double("sail_cbf"), prepared_double("sail_cbf")
    fresh = b.proposal.center
    b.proposal.center = lambda mb, a_st, kappa, step=None: fresh(mb, a_st, kappa)   # ignores any step given
    order = [1, 2, 0]
    _, start_a = gap_diagnostics(a.proposal, mb, 0.5, 3.0)
    calls.clear()
    sa = happo_step(a, mb, 0.5, 3.0, order=order, start=start_a)
    assert len(calls) == 2            # the refreshes after carriers 1 and 2; their graphs reuse them
    _, start_b = gap_diagnostics(b.proposal, mb, 0.5, 3.0)
    sb = happo_step(b, mb, 0.5, 3.0, order=order, start=start_b)
    torch.testing.assert_close(flat(a), flat(b), rtol=1e-9, atol=1e-12)
    for i in order:
        torch.testing.assert_close(a.last_happo_factors[i], b.last_happo_factors[i], rtol=1e-9, atol=1e-12)
    assert sa == pytest.approx(sb, rel=1e-9, abs=1e-12)
