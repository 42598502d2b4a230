"""TALO's gap in closed form (common/algos/gap_closed_form.py) against the autograd graph of
the same functions with nothing compiled in it (``forest_forward_reference`` for the trees,
``reference_surrogates`` for the chain): g_ind, g_team, W_gap and grad W for every method,
against the behaviour policy and a lagged start, float64 (to 1e-10) and float32 parameters
(to float32 rounding), with human blocks and k-sparse trees; and the trees' tape
(``ForestTape``: action, backward, double backward with the split vectors' normalization)
against autograd on random cotangents and directions."""
import dataclasses

import numpy as np
import pytest
import torch

from common.algos import surrogate_chain
from common.algos.config import AlgoConfig
from common.algos.gap_closed_form import cotangent_sets
from common.algos.methods import make_method
from common.algos.synthetic import BanditTask, collect
from common.policy import tree_torch
from common.policy.tree import TreeConfig
from common.policy.tree_torch import TeamPolicy, forest_forward_reference

METHODS = ["sage", "talo_cbf", "sail_cbf", "joint_cbf", "happo", "happo_cbf"]


def _rel(a, b):
    a, b = torch.as_tensor(a).double(), torch.as_tensor(b).double()
    return float((a - b).abs().max() / b.abs().max().clamp(min=1e-300))


def _learner(name, dtype, sparse=False, seed=3):
    cfg = AlgoConfig(seed=seed, split_k=3 if sparse else 0, leaf_k=4 if sparse else 0)
    task = BanditTask(obs_dim=16, seed=seed, n_rows=12, human_rate=0.15)
    method = make_method(name, cfg, 16, 48)
    batch = collect(method, task, 16, 8, 0.5, np.random.default_rng(seed))
    method.policy.to(dtype)
    data, _ = method._prepare(batch)
    data = method.proposal.prepared(data)
    lagged = data.logp_old + 0.2 * torch.randn(data.logp_old.shape, generator=torch.Generator().manual_seed(1),
                                               dtype=data.logp_old.dtype)
    return method, data, lagged


def _gaps(method, mb, closed_form):
    method.proposal.closed_form = closed_form
    a_st, _, behaviour, start = method.proposal.start_point(mb, 0.3, 5.0)
    out = [*method.proposal.gap(a_st, behaviour, with_hvp=True), *method.proposal.gap(a_st, start, with_hvp=False)[:3]]
    return out, behaviour


def _reference_gaps(method, mb, monkeypatch):
    with monkeypatch.context() as patch:
        patch.setattr(tree_torch, "forest_forward", forest_forward_reference)
        patch.setattr(surrogate_chain, "chain_surrogates", surrogate_chain.reference_surrogates)
        return _gaps(method, mb, closed_form=False)


@pytest.mark.parametrize("sparse", [False, True])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 1e-5)])
@pytest.mark.parametrize("name", METHODS)
def test_closed_form_gap_equals_autograd_on_the_reference_graph(name, dtype, tol, sparse, monkeypatch):
    method, data, lagged = _learner(name, dtype, sparse)
    checked = 0
    for logp_start in (None, lagged):
        mb = dataclasses.replace(data, logp_start=logp_start)
        (closed, behaviour), (ref, _) = _gaps(method, mb, closed_form=True), _reference_gaps(method, mb, monkeypatch)
        assert behaviour.taped is not None
        for key, a, b in zip(("g_ind", "g_team", "w_gap", "grad_w", "start g_ind", "start g_team", "start w_gap"),
                             closed, ref):
            if b is None:                            # no HVP on the identity center's trivial gap
                continue
            assert torch.as_tensor(a).dtype == torch.as_tensor(b).dtype == dtype, key
            if float(torch.as_tensor(b).abs().max()) < 1e-12:    # W_gap at ratio 1 without SAIL's coupling
                assert float(torch.as_tensor(a).abs().max()) < 1e-12, key
                continue
            assert _rel(a, b) < tol, (key, _rel(a, b))
            checked += 1
    assert checked >= 8       # the comparison compared something: both references, both gradients


@pytest.mark.parametrize("name", ["sage", "happo"])
def test_individual_gradient_is_each_carriers_own_surrogate_gradient(name):
    method, data, lagged = _learner(name, torch.float64)
    mb = dataclasses.replace(data, logp_start=lagged)
    _, behaviour = _gaps(method, mb, closed_form=True)
    g_ind = method.proposal.individual_gradient(behaviour)
    (_, graph) = _gaps(method, mb, closed_form=False)
    expected = torch.cat([torch.cat([g.reshape(-1) for g in torch.autograd.grad(L, group, retain_graph=True)])
                          for L, group in zip(graph.L_ind, method.groups)])
    assert float(expected.abs().max()) > 0 and _rel(g_ind, expected) < 1e-10
    assert method.proposal.individual_gradient(graph) is None      # no tapes: nothing to read


def test_cotangent_sets_pick_the_surrogates_they_name():
    d = cotangent_sets(2, 3, 1, "d")
    assert d.shape == (3, 2, 4) and d[:, 0].sum() == 0
    assert [list(d[j, 1]) for j in range(3)] == [[1, 0, 0, -1], [0, 1, 0, -1], [0, 0, 1, -1]]
    assert cotangent_sets(2, 3, 0, "team").tolist() == [[[0, 0, 0, 1], [0, 0, 0, 0]]]
    assert cotangent_sets(1, 3, 0, "ind")[:, 0, :3].tolist() == np.eye(3).tolist()
    with pytest.raises(ValueError, match="unknown"):
        cotangent_sets(1, 3, 0, "both")


@pytest.mark.parametrize("split_k,leaf_k", [(0, 0), (2, 3)])
@pytest.mark.parametrize("seed", range(3))
def test_forest_tape_is_autograd_of_the_reference_forest(seed, split_k, leaf_k):
    """The trees' action bitwise, and for a random cotangent q and direction V the backward
    and both halves of the double backward (d/dq along V, Hess(q . z) V) against autograd on
    ``forest_forward_reference`` (every leaf, the normalization as ops), float64."""
    torch.manual_seed(seed)
    team = TeamPolicy(3, 7, config=TreeConfig(depth=4, split_k=split_k, leaf_k=leaf_k)).double()
    with torch.no_grad():   # spread the routes so that every kind of leaf is reached
        for t in team.trees:
            t.b.mul_(0.3)
            t.W.mul_(torch.rand(t.W.shape[0], 1, dtype=torch.float64) + 0.5)   # rows off unit norm
    obs = torch.randn(40, 3, 7, dtype=torch.float64)
    tau = 0.4
    tape = team.taped(obs, tau)
    assert torch.equal(tape.action, team(obs, tau).action)
    params = [[t.W, t.b, t.K, t.beta] for t in team.trees]
    flat = [p for g in params for p in g]
    gen = torch.Generator().manual_seed(seed + 10)
    q = torch.randn(tape.action.shape, generator=gen, dtype=torch.float64)
    V = [torch.randn(p.shape, generator=gen, dtype=torch.float64) for p in flat]
    action = forest_forward_reference(team.trees, obs.transpose(0, 1), tau)[0].transpose(0, 1).reshape(40, -1)
    grads = torch.autograd.grad((action * q).sum(), flat, create_graph=True)
    qv = q.clone().requires_grad_(True)
    action_q = forest_forward_reference(team.trees, obs.transpose(0, 1), tau)[0].transpose(0, 1).reshape(40, -1)
    grads_q = torch.autograd.grad((action_q * qv).sum(), flat, create_graph=True)
    dz_ref = torch.autograd.grad(sum((g * v).sum() for g, v in zip(grads_q, V)), qv)[0]
    hess_ref = torch.autograd.grad(sum((g * v).sum() for g, v in zip(grads, V)), flat)

    def stacked(xs, k):
        return np.stack([x.detach().numpy() for x in xs[k::4]])

    vjp = tape.vjp(q.numpy())
    dz, hess = tape.hvp(q.numpy(), [stacked(V, k) for k in range(4)], tape.unit_vjp(q.numpy())[0])
    for k in range(4):
        ref = stacked(grads, k)
        assert np.abs(ref).max() > 0
        np.testing.assert_allclose(vjp[k], ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
        ref_h = stacked(hess_ref, k)
        assert np.abs(ref_h).max() > 0
        np.testing.assert_allclose(hess[k], ref_h, rtol=1e-10, atol=1e-11 * np.abs(ref_h).max())
    np.testing.assert_allclose(dz, dz_ref.numpy(), rtol=1e-12, atol=1e-12 * float(dz_ref.abs().max()))


def test_the_closed_form_needs_the_trees_parameters_in_their_order():
    method = make_method("sage", AlgoConfig(), 6, 0)
    proposal_map = type(method.proposal)
    tree = method.policy.trees[0]
    tree.extra = torch.nn.Parameter(torch.zeros(1))
    with pytest.raises(ValueError, match="parameters must be"):
        proposal_map(method.policy, True, "implicit", 0.2)
