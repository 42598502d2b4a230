"""Hard oblique tree actors: routing, straight-through gradients, numpy twin, export/import."""
import numpy as np
import pytest
import torch

from common.policy.tree import (
    FORMAT_VERSION,
    InvalidParams,
    TreeConfig,
    carrier_params,
    team_forward_np,
    tree_forward_np,
    validate_params,
)
from common.policy.tree_torch import HardObliqueTree, TeamPolicy


def _team(n=3, obs_dim=11, depth=4, seed=0, **cfg):
    torch.manual_seed(seed)
    team = TeamPolicy(n, obs_dim, depth=depth, config=TreeConfig(**cfg))
    with torch.no_grad():  # non-trivial leaves so that leaf actions differ visibly
        for tree in team.trees:
            tree.K.normal_(0.0, 0.5)
            tree.beta.normal_(0.0, 0.5)
    return team


def _reference_route(W, b, o):
    """Independent per-sample router straight from Eq. (hard_gate), float64."""
    node, path = 0, []
    n_internal = len(b)
    while node < n_internal:
        w = W[node] / np.sqrt(np.sum(W[node] ** 2))
        right = float(np.dot(w, o)) > b[node]
        path.append((node, right))
        node = 2 * node + 2 if right else 2 * node + 1
    return node - n_internal, path


def _leaf_action(p, leaf, o):
    return p["c_a"] + p["s_a"] * np.tanh(p["K"][leaf].astype(np.float64) @ o + p["beta"][leaf])


@pytest.mark.parametrize("depth", [1, 2, 4, 5])
def test_hard_routing_and_action_match_reference(depth):
    team = _team(depth=depth, seed=depth)
    params = team.export_params()
    obs = np.random.default_rng(depth).normal(size=(64, 3, 11)).astype(np.float32)
    out = team(torch.from_numpy(obs), tau=0.3)
    for i in range(3):
        p = {k: v.astype(np.float64) for k, v in carrier_params(params, i).items()}
        for bi in range(len(obs)):
            o = obs[bi, i].astype(np.float64)
            leaf, path = _reference_route(p["W"], p["b"], o)
            assert out.leaf[bi, i].item() == leaf
            assert out.nodes[bi, i].tolist() == [n for n, _ in path]
            assert out.sides[bi, i].tolist() == [s for _, s in path]
            np.testing.assert_allclose(out.action[bi, 3 * i : 3 * i + 3].detach().numpy(), _leaf_action(p, leaf, o), atol=1e-6)
    assert out.action.shape == (64, 9) and out.leaf.shape == (64, 3)
    assert out.nodes.shape == (64, 3, depth) and out.sides.dtype == torch.bool


def test_st_weights_are_exactly_one_hot_and_action_exactly_the_leaf_action():
    torch.manual_seed(1)
    tree = HardObliqueTree(7, depth=4)
    obs = torch.randn(300, 7)
    margins = tree.gate_margins(obs)
    out = tree(obs, tau=0.1)
    weight = tree.st_leaf_weights(margins, 0.1)
    onehot = torch.nn.functional.one_hot(out.leaf, tree.n_leaves).double()
    assert torch.equal(weight, onehot)
    leaf_actions = tree.leaf_actions(obs)
    assert torch.equal(out.action, leaf_actions[torch.arange(300), out.leaf].float())


@pytest.mark.parametrize("tau", [0.05, 1.0])
def test_straight_through_gradients_match_analytic_formula(tau):
    """d(v.a)/d margin_k = v.(A_right(k) - A_left(k)) * p_k (1 - p_k) / tau on the routed path,
    where A_side(k) is the action of the leaf reached by taking `side` at k and hard gates below."""
    team = _team(n=1, obs_dim=6, depth=3, seed=2)
    tree = team.trees[0]
    obs = torch.randn(5, 6, generator=torch.Generator().manual_seed(3))
    v = torch.tensor([0.3, -1.2, 0.7])
    for bi in range(len(obs)):
        tree.zero_grad()
        out = tree(obs[bi : bi + 1], tau)
        (out.action[0] @ v).backward()
        p = {k: v_.astype(np.float64) for k, v_ in carrier_params(team.export_params(), 0).items()}
        o = obs[bi].double().numpy()
        n_int = len(p["b"])
        w = p["W"] / np.linalg.norm(p["W"], axis=1, keepdims=True)
        margins = w @ o - p["b"]
        grad_b = np.zeros(n_int)
        grad_W = np.zeros_like(p["W"])
        _, path = _reference_route(p["W"], p["b"], o)
        for node, _ in path:
            ends = []
            for first in (2 * node + 2, 2 * node + 1):  # right then left subtree, hard below
                k = first
                while k < n_int:
                    k = 2 * k + 2 if margins[k] > 0 else 2 * k + 1
                ends.append(_leaf_action(p, k - n_int, o) @ v.double().numpy())
            pk = 1.0 / (1.0 + np.exp(-margins[node] / tau))
            dm = (ends[0] - ends[1]) * pk * (1.0 - pk) / tau
            grad_b[node] = -dm
            grad_W[node] = dm * (o - (w[node] @ o) * w[node]) / np.linalg.norm(p["W"][node])
        np.testing.assert_allclose(tree.b.grad.numpy(), grad_b, rtol=1e-4, atol=1e-7)
        np.testing.assert_allclose(tree.W.grad.numpy(), grad_W, rtol=1e-4, atol=1e-7)
        # leaf controllers: only the routed leaf receives gradient
        leaf = out.leaf.item()
        others = [l for l in range(tree.n_leaves) if l != leaf]
        assert torch.all(tree.K.grad[others] == 0) and torch.all(tree.beta.grad[others] == 0)
        assert torch.any(tree.K.grad[leaf] != 0)


def test_numpy_twin_matches_torch_on_random_inputs():
    for seed, (obs_dim, depth) in enumerate([(5, 1), (11, 4), (40, 4), (23, 6)]):
        team = _team(obs_dim=obs_dim, depth=depth, seed=seed)
        obs = (3.0 * np.random.default_rng(seed).normal(size=(500, 3, obs_dim))).astype(np.float32)
        out = team(torch.from_numpy(obs), tau=1.0)
        a, leaf, nodes, sides = team_forward_np(team.export_params(), obs)
        np.testing.assert_allclose(a, out.action.detach().numpy(), atol=1e-6, rtol=0)
        assert np.array_equal(leaf, out.leaf.numpy())
        assert np.array_equal(nodes, out.nodes.numpy()) and np.array_equal(sides, out.sides.numpy())


def test_near_threshold_routing_agrees_under_float64_policy():
    """Walk float32 observations one ulp at a time across the root threshold: the two
    neighbours straddle it with |margin| ~ 1e-8, where float32 margins would be unreliable."""
    team = _team(n=1, obs_dim=9, depth=3, seed=5)
    params = team.export_params()
    p = carrier_params(params, 0)
    W, b = p["W"].astype(np.float64), p["b"].astype(np.float64)
    w0 = W[0] / np.linalg.norm(W[0])
    j = int(np.argmax(np.abs(w0)))
    rng = np.random.default_rng(0)
    points, margins64 = [], []
    for _ in range(200):
        o = rng.normal(size=9)
        o -= (w0 @ o - b[0]) * w0  # onto the root hyperplane (float64)
        o = o.astype(np.float32)
        m = lambda x: w0 @ x.astype(np.float64) - b[0]  # noqa: E731
        direction = np.float32(np.inf if (m(o) <= 0) == (w0[j] > 0) else -np.inf)
        for _ in range(1000):  # step coordinate j by ulps until the margin changes sign
            nxt = o.copy()
            nxt[j] = np.nextafter(o[j], direction)
            if (m(nxt) > 0) != (m(o) > 0):
                points += [o, nxt]
                margins64 += [m(o), m(nxt)]
                break
            o = nxt
    obs = np.stack(points)[:, None, :]
    margins64 = np.array(margins64)
    assert len(points) == 400 and np.max(np.abs(margins64)) < 1e-6
    out = team(torch.from_numpy(obs), tau=1.0)
    _, leaf, nodes, sides = team_forward_np(params, obs)
    assert np.array_equal(leaf, out.leaf.numpy()) and np.array_equal(sides, out.sides.numpy())
    assert np.array_equal(sides[:, 0, 0], margins64 > 0)  # the root side is the float64 one
    # the policy matters: plain float32 margins get some of these points wrong
    m32 = obs[:, 0, :] @ (p["W"][0] / np.linalg.norm(p["W"][0])).astype(np.float32) - p["b"][0]
    assert np.any((m32 > 0) != (margins64 > 0))


def test_untrained_policy_is_a_weak_random_controller():
    torch.manual_seed(0)
    team = TeamPolicy(3, 40)
    obs = torch.randn(2000, 3, 40)
    out = team(obs)
    a = out.action.detach()
    assert 0.01 < a.abs().mean() < 0.2 and a.std(0).min() > 0.01
    assert len(torch.unique(out.leaf[:, 0])) >= 12  # routing spreads over the 16 leaves
    for tree in team.trees:
        assert torch.allclose(tree.W.norm(dim=1), torch.ones(15))
        assert torch.all(tree.beta == 0)


def test_team_trees_are_independent_and_log_std_is_a_parameter():
    team = _team()
    names = {n for n, _ in team.named_parameters()}
    assert {f"trees.{i}.log_std" for i in range(3)} <= names
    ptrs = [p.data_ptr() for p in team.parameters()]
    assert len(ptrs) == len(set(ptrs))  # no sharing
    out = team(torch.randn(8, 3, 11))
    out.action[:, 0:3].sum().backward()
    assert all(p.grad is None or torch.all(p.grad == 0) for p in team.trees[1].parameters())
    assert team.trees[0].K.grad.abs().sum() > 0
    assert team.log_std.shape == (9,) and team.log_std.requires_grad


@pytest.mark.parametrize("split_k,leaf_k", [(0, 0), (1, 2)])
def test_batched_team_forward_equals_each_tree_alone(split_k, leaf_k):
    """The team runs its trees as one batched forward (common.policy.tree_torch.forest_forward
    with a carrier axis); each tree alone is the same function with N = 1. Values, routes,
    gradients and second derivatives (the HVP TALO takes) must agree carrier by carrier."""
    team = _team(depth=3, seed=7, split_k=split_k, leaf_k=leaf_k).double()
    obs = torch.randn(40, 3, 11, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    v = torch.randn(40, 9, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    params = list(team.parameters())

    def grad_and_hvp(action):
        loss = (torch.tanh(action) * v).sum()
        g = torch.autograd.grad(loss, params, create_graph=True, allow_unused=True)
        g = torch.cat([(torch.zeros_like(p) if x is None else x).reshape(-1) for x, p in zip(g, params)])
        hvp = torch.autograd.grad(0.5 * g.pow(2).sum(), params, allow_unused=True)
        return g.detach(), torch.cat([(torch.zeros_like(p) if x is None else x).reshape(-1)
                                      for x, p in zip(hvp, params)])

    batched = team(obs, tau=0.4)
    alone = [tree(obs[:, i], tau=0.4) for i, tree in enumerate(team.trees)]
    assert torch.equal(batched.action, torch.cat([o.action for o in alone], dim=1))
    for key in ("leaf", "nodes", "sides"):
        assert torch.equal(getattr(batched, key), torch.stack([getattr(o, key) for o in alone], dim=1))
    g_b, h_b = grad_and_hvp(batched.action)
    g_a, h_a = grad_and_hvp(torch.cat([o.action for o in alone], dim=1))
    assert g_b.norm() > 0 and h_b.norm() > 0
    torch.testing.assert_close(g_b, g_a, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(h_b, h_a, rtol=1e-12, atol=1e-14)


def test_team_forward_rejects_a_wrong_observation_size():
    with pytest.raises(ValueError, match="obs must be"):
        _team()(torch.randn(4, 3, 10))


def test_export_import_roundtrip():
    team = _team(seed=1)
    params = team.export_params()
    assert params["format_version"] == FORMAT_VERSION
    assert all(v.dtype == np.float32 for k, v in params.items() if k != "format_version")
    assert set(params) == {"format_version"} | {f"carrier_{i}/{n}" for i in range(3) for n in ("W", "b", "K", "beta", "log_std", "c_a", "s_a")}
    other = _team(seed=2)
    obs = torch.randn(50, 3, 11)
    assert not torch.equal(other(obs).action, team(obs).action)
    other.load_params(params)
    assert torch.equal(other(obs).action, team(obs).action)
    clone = TeamPolicy.from_params(params)
    assert torch.equal(clone(obs).action, team(obs).action)
    assert validate_params(params) == (3, 11, 3, 4)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda p: p.pop("carrier_1/K"), "carrier_1 lacks"),
        (lambda p: p.pop("format_version"), "format_version"),
        (lambda p: p.__setitem__("format_version", np.asarray(2.0)), "not supported"),
        (lambda p: p.__setitem__("carrier_0/b", np.zeros(14, np.float32)), r"carrier_0/b has shape"),
        (lambda p: p.__setitem__("carrier_2/W", p["carrier_2/W"][:7]), r"carrier_2"),
        (lambda p: p["carrier_0/beta"].__setitem__((0, 0), np.nan), "NaN"),
        (lambda p: p.__setitem__("carrier_0/K", p["carrier_0/K"].astype(np.int64)), "float array"),
        (lambda p: p["carrier_1/W"].__setitem__(3, 0.0), "zero row"),
        (lambda p: p.__setitem__("carrier_0/extra", np.zeros(1)), "unknown params key"),
        (lambda p: p.__setitem__("carrier_5/W", p["carrier_0/W"]), "carrier"),
    ],
)
def test_import_rejects_bad_params(mutate, message):
    team = _team()
    params = {k: v.copy() for k, v in team.export_params().items()}
    mutate(params)
    with pytest.raises(InvalidParams, match=message):
        team.load_params(params)
    with pytest.raises(InvalidParams):
        team_forward_np(params, np.zeros((1, 3, 11), np.float32))


def test_import_rejects_other_shape_team():
    params = _team(obs_dim=11, depth=3).export_params()
    with pytest.raises(InvalidParams, match="shape spec"):
        _team(obs_dim=11, depth=4).load_params(params)


def test_bad_inputs():
    team = _team()
    with pytest.raises(ValueError, match="obs must be"):
        team(torch.zeros(4, 2, 11))
    with pytest.raises(ValueError, match="tau"):
        team(torch.zeros(4, 3, 11), tau=0.0)
    with pytest.raises(ValueError, match="obs must be"):
        team_forward_np(team.export_params(), np.zeros((4, 3, 10), np.float32))
    with pytest.raises(ValueError, match="obs must be"):
        tree_forward_np(carrier_params(team.export_params(), 0), np.zeros(11))
