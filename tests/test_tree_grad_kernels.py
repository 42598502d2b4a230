"""The learner's compiled hard-tree path (tree_torch.TreeCore over
common/policy/tree_grad_kernels.py) against its reference, the same function as one
autograd graph (tree_torch.forest_forward_reference): values and routes, gradients and
Hessian-vector products, on random batches of every tree shape the config allows, and
TALO's whole gap (g_ind, g_team, W_gap, grad W) on a learner minibatch."""
import dataclasses

import numpy as np
import pytest
import torch

from common.algos.config import AlgoConfig
from common.algos.methods import flush_subnormals, make_method, subnormals_flushed
from common.algos.synthetic import BanditTask, collect
from common.policy import tree_torch
from common.policy.tree import TreeConfig
from common.policy.tree_torch import TeamPolicy, forest_forward, forest_forward_reference

SHAPES = [  # (split_k, leaf_k, depth)
    (1, 0, 4), (0, 0, 4), (2, 3, 3), (1, 0, 1), (0, 2, 5), (3, 0, 2),
]


def _team(split_k, leaf_k, depth, seed=0, obs_dim=12):
    torch.manual_seed(seed)
    cfg = TreeConfig(depth=depth, split_k=split_k, leaf_k=leaf_k, b_init_scale=0.3, k_init_scale=1.0)
    return TeamPolicy(3, obs_dim, config=cfg).double()   # float64 parameters: compare to ~1e-10


def _derivatives(forward, trees, obs, tau, seed):
    """Value, route, gradient and HVP of a nonlinear loss of the action (so the cotangent
    depends on the parameters, as TALO's surrogates do)."""
    params = [p for t in trees for p in t.parameters()]
    action, leaf, nodes, sides = forward(trees, obs, tau)
    gen = torch.Generator().manual_seed(seed)
    q = torch.randn(action.shape, generator=gen, dtype=torch.float64)
    loss = (torch.sin(3.0 * action) * q).sum() + (action ** 2).sum()
    grads = torch.autograd.grad(loss, params, create_graph=True, allow_unused=True)
    flat = torch.cat([(torch.zeros_like(p) if g is None else g).reshape(-1) for g, p in zip(grads, params)])
    v = torch.randn(flat.shape, generator=gen, dtype=torch.float64)
    hvp = torch.autograd.grad(flat @ v, params, allow_unused=True)
    hvp = torch.cat([(torch.zeros_like(p) if h is None else h).reshape(-1) for h, p in zip(hvp, params)])
    return action.detach(), (leaf, nodes, sides), flat.detach(), hvp


def _rel(a, b):
    return float((a - b).abs().max() / b.abs().max().clamp(min=1e-300))


@pytest.mark.parametrize("split_k,leaf_k,depth", SHAPES)
@pytest.mark.parametrize("tau", [1.0, 0.1])
def test_kernels_match_the_autograd_reference(split_k, leaf_k, depth, tau):
    trees = list(_team(split_k, leaf_k, depth).trees)
    obs = torch.randn(3, 300, 12, generator=torch.Generator().manual_seed(depth), dtype=torch.float64)
    fast = _derivatives(forest_forward, trees, obs, tau, seed=1)
    ref = _derivatives(forest_forward_reference, trees, obs, tau, seed=1)
    assert _rel(fast[0], ref[0]) < 1e-12
    for a, b in zip(fast[1], ref[1]):
        assert torch.equal(a, b)
    assert _rel(fast[2], ref[2]) < 1e-10
    assert _rel(fast[3], ref[3]) < 1e-10
    assert float(ref[3].abs().max()) > 0      # the comparison has something to compare


def test_one_tree_and_the_team_take_the_same_path():
    """HardObliqueTree.forward (HAPPO's per-carrier forward) goes through the same kernels."""
    team = _team(1, 0, 4)
    obs = torch.randn(64, 3, 12, dtype=torch.float64)
    joint = team(obs, 0.5).action
    for i, tree in enumerate(team.trees):
        assert torch.equal(tree(obs[:, i], 0.5).action, joint[:, 3 * i:3 * i + 3])


def test_float32_parameters_get_float32_gradients():
    team = TeamPolicy(3, 12, config=TreeConfig(depth=3))
    obs = torch.randn(32, 3, 12)
    team(obs, 0.5).action.pow(2).sum().backward()
    for tree in team.trees:
        for p in (tree.W, tree.b, tree.K, tree.beta):   # log_std is not in the action
            assert p.grad is not None and p.grad.dtype == torch.float32 and bool(torch.isfinite(p.grad).all())


@pytest.mark.parametrize("name", ["sage", "talo_cbf", "sail_cbf"])
def test_talo_gap_matches_the_reference_path(name, monkeypatch):
    """g_ind, g_team, W_gap and TALO's HVP on one learner minibatch, compiled path vs the
    reference graph (float32 parameters: agreement to float32 rounding of the gradients)."""
    cfg = AlgoConfig(seed=3)
    task = BanditTask(obs_dim=16, seed=3, n_rows=12, human_rate=0.1)
    method = make_method(name, cfg, 16, 48)
    method.proposal.closed_form = False   # the graph with TreeCore vs the tree as ops
    batch = collect(method, task, 16, 8, 0.5, np.random.default_rng(3))
    data, _ = method._prepare(batch)
    mb = dataclasses.replace(data, logp_start=None)

    def gap():
        a_st, _, behaviour, _ = method.proposal.start_point(mb, 0.3, 5.0)
        return method.proposal.gap(a_st, behaviour, with_hvp=True)

    fast = gap()
    monkeypatch.setattr(tree_torch, "forest_forward", forest_forward_reference)
    ref = gap()
    for a, b in zip(fast, ref):
        b = torch.as_tensor(b)
        assert float(b.abs().max()) > 0
        assert _rel(torch.as_tensor(a).double(), b.double()) < 1e-5


def test_the_update_leaves_the_subnormal_flag_as_it_found_it():
    tiny = torch.tensor([1e-310], dtype=torch.float64)
    assert not subnormals_flushed() and float(tiny * 1.0) > 0   # the default: kept
    with flush_subnormals():
        assert subnormals_flushed() and float(tiny * 1.0) == 0.0
    assert not subnormals_flushed()
    cfg = AlgoConfig(seed=0, epochs=1)
    method = make_method("happo", cfg, 16, 48)
    batch = collect(method, BanditTask(obs_dim=16, seed=0, n_rows=8), 8, 4, 0.5, np.random.default_rng(0))
    method.update(batch, 0.5)
    assert not subnormals_flushed()
