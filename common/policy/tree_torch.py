"""Torch twin of the hard oblique trees (common/policy/tree.py): the learner's
``HardObliqueTree`` per carrier and the ``TeamPolicy`` of three of them, with
straight-through gates (Eq. st_gate). Kept apart from the numpy module so that
actor processes, which only need the numpy forward, never import torch.
"""
from __future__ import annotations

import json
import math
from collections.abc import Mapping

import numpy as np
import torch
from torch import nn
from torch.autograd.function import once_differentiable

from common.policy.tree import (
    FORMAT_VERSION,
    PARAM_NAMES,
    InvalidParams,
    ParamsSpec,
    TreeConfig,
    TreeOutput,
    validate_params,
)
from common.policy.tree_grad_kernels import tree_st_forward, tree_st_hvp, tree_st_vjp


def top_k_mask(x: torch.Tensor, k: int) -> torch.Tensor:
    """1 on the ``k`` largest |x| entries of each row (last axis), 0 elsewhere;
    all ones when ``k`` is 0 (dense) or >= the row length."""
    if k <= 0 or k >= x.shape[-1]:
        return torch.ones_like(x)
    idx = x.abs().topk(k, dim=-1).indices
    return torch.zeros_like(x).scatter_(-1, idx, 1.0)


def st_top_k(x: torch.Tensor, k: int) -> torch.Tensor:
    """Forward: ``x`` with all but its k largest |x| per row zeroed (what actors
    run); backward: the identity, so a dropped feature whose gradient keeps
    pushing can grow past a kept one and take its place (as Eq. st_gate does
    for the gates). Projecting the parameter itself would freeze a one-feature
    split on its initial feature: the unit-norm gate gives the kept weight no
    gradient and the dropped ones are zeroed after every step."""
    if k <= 0 or k >= x.shape[-1]:
        return x
    mask = top_k_mask(x.detach(), k)
    return x * mask + (x - x.detach()) * (1.0 - mask)


# ----------------------------------------------------------------------------- the forward, batched over carriers
# Every function below takes a leading carrier axis N (N = 1 for one tree), so the
# team's three trees run as one set of batched ops: the learner's backward and
# double backward (TALO's HVP) then walk one graph of N-times larger tensors
# instead of N graphs, which is what their cost scales with.


def gate_margins(W, b, obs):
    """w_k.o - b_k, float64 [N, B, n_internal] from W [N, n_internal, O], b [N, n_internal],
    obs [N, B, O]; w_k = W_k / ||W_k|| (Eq. hard_gate)."""
    W = W.double()
    w = W / torch.linalg.vector_norm(W, dim=-1, keepdim=True)
    return torch.baddbmm(-b.double()[:, None, :], obs.double(), w.transpose(1, 2))


def leaf_preactivations(K, beta, obs):
    """K_l o + beta_l for every leaf, float64 [N, B, n_leaves, A] from K [N, L, A, O]."""
    N, L, A, O = K.shape
    u = torch.baddbmm(beta.double().reshape(N, 1, L * A), obs.double(),
                      K.double().reshape(N, L * A, O).transpose(1, 2))
    return u.reshape(N, -1, L, A)


def route(margins, depth: int):
    """Hard routing (Eq. hard_gate) of margins [N, B, n_internal]: leaf [N, B],
    nodes [N, B, D], sides [N, B, D] (True = right)."""
    hard = margins > 0
    node = torch.zeros(margins.shape[:2], dtype=torch.int64, device=margins.device)
    nodes, sides = [], []
    for _ in range(depth):
        side = hard.gather(2, node[..., None])[..., 0]
        nodes.append(node)
        sides.append(side)
        node = 2 * node + 1 + side.long()
    return node - (2**depth - 1), torch.stack(nodes, -1), torch.stack(sides, -1)


def st_leaf_weights(margins, tau: float, depth: int):
    """Path products of g^ST (right) / 1 - g^ST (left), [N, B, n_leaves] float64;
    the forward value is exactly the hard one-hot."""
    p = torch.sigmoid(margins / tau)
    g_st = (margins > 0).to(p.dtype) + (p - p.detach())  # Eq. (st_gate), forward exactly hard
    N, B = margins.shape[:2]
    weight = torch.ones_like(margins[..., :1])
    for level in range(depth):
        g = g_st[..., 2**level - 1 : 2**(level + 1) - 1]  # nodes of this level, left to right
        weight = torch.stack([weight * (1.0 - g), weight * g], dim=-1).reshape(N, B, -1)
    return weight


def _stacked(trees, name):
    return torch.stack([getattr(t, name) for t in trees]) if len(trees) > 1 else getattr(trees[0], name)[None]


def forest_forward(trees, obs, tau: float):
    """N trees of one shape on obs [N, B, O]: action [N, B, A] (parameter dtype), leaf
    [N, B], nodes and sides [N, B, D]. The action is sum_l weight_l (c_a + s_a tanh(K_l o
    + beta_l)) (Eq. hard_tree_policy), written c_a + s_a sum_l weight_l tanh(.): the same
    value (the weights are exactly one-hot) and the same derivatives (sum_l weight_l is
    identically 1). The straight-through top-k and the split vectors' normalization run
    here in torch; the routed leaf sum, its gradient and its double backward in the
    compiled ``TreeCore`` (common/policy/tree_grad_kernels.py), which
    ``forest_forward_reference`` (the same function as one autograd graph) is tested against."""
    if not float(tau) > 0:
        raise ValueError(f"tree: tau must be > 0, got {tau}")
    first = trees[0]
    _, w, b, K, beta = _core_inputs(trees)
    mixed, leaf, nodes, sides = TreeCore.apply(w, b, K, beta, obs.double(), float(tau), first.depth)
    action = _stacked(trees, "c_a").double()[:, None] + _stacked(trees, "s_a").double()[:, None] * mixed
    return action.to(first.K.dtype), leaf, nodes, sides


def _core_inputs(trees):
    """``TreeCore``'s float64 inputs from the trees' parameters: the straight-through top-k of
    W and K, the norms r of W's rows and the unit split vectors w = W / r (Eq. hard_gate)."""
    first = trees[0]
    W = st_top_k(_stacked(trees, "W"), first.split_k).double()
    r = torch.linalg.vector_norm(W, dim=-1, keepdim=True)
    K = st_top_k(_stacked(trees, "K"), first.leaf_k).double()
    return r, W / r, _stacked(trees, "b").double(), K, _stacked(trees, "beta").double()


class ForestTape:
    """N trees of one shape at one forward, without an autograd graph, and the closed-form
    derivatives of their stacked actions z = c_a + s_a mix [B, N*A] in the raw parameters
    (W, b, K, beta, each stacked [N, ...]; float64 numpy): ``vjp`` is what autograd's backward
    of ``forest_forward`` gives, ``hvp`` its double backward. Around ``TreeCore``'s kernels only
    the action scale s_a and the split vectors' normalization w = W / r are written out (the
    straight-through top-k passes values and derivatives through unchanged):

        grad_W = (grad_w - w (w . grad_w)) / r,    dw = (V_W - w (w . V_W)) / r,
        d grad_W [V_W] = -(dw (w . grad_w) + w (dw . grad_w)) / r - grad_W (w . V_W) / r."""

    def __init__(self, trees, obs, tau: float):
        first = trees[0]
        with torch.no_grad():
            r, w, b, K, beta = _core_inputs(trees)
            self.obs = _numpy(obs.double())
            self.w, self.r, self.K, self.beta = _numpy(w), _numpy(r), _numpy(K), _numpy(beta)
            mix, self.margins, leaf, self.nodes, self.sides, _, self.t_near, self.g1 = tree_st_forward(
                self.w, _numpy(b), self.K, self.beta, self.obs, first.depth, float(tau), True)
            self.leaf, self.tau, self.depth = leaf, float(tau), first.depth
            self.s_a = _numpy(_stacked(trees, "s_a").double())                     # [N, A]
            action = _stacked(trees, "c_a").double()[:, None] + torch.from_numpy(self.s_a)[:, None] \
                * torch.from_numpy(mix)
            N, B, A = mix.shape
            self.action = action.to(first.K.dtype).transpose(0, 1).reshape(B, N * A)

    def _mix_cotangent(self, q_z):
        N, A = self.s_a.shape
        return np.ascontiguousarray(q_z.reshape(-1, N, A).transpose(1, 0, 2)) * self.s_a[:, None]

    def _from_unit(self, g_w):
        return (g_w - self.w * (self.w * g_w).sum(-1, keepdims=True)) / self.r

    def unit_vjp(self, q_z):
        """grad of sum_b q_z[b] . z[b] in (w, b, K, beta): the split vectors' block in the unit
        vectors w (what ``hvp`` reads), the others in the parameters themselves."""
        return tree_st_vjp(self._mix_cotangent(q_z), self.obs, self.leaf, self.nodes, self.sides,
                           self.t_near, self.g1, self.w.shape, self.K.shape)

    def raw(self, unit):
        """``unit_vjp``'s answer in the raw parameters (W, b, K, beta)."""
        gw, gb, gK, gbeta = unit
        return self._from_unit(gw), gb, gK, gbeta

    def vjp(self, q_z):
        """grad of sum_b q_z[b] . z[b] in (W, b, K, beta) for q_z [B, N*A]."""
        return self.raw(self.unit_vjp(q_z))

    def hvp(self, q_z, V, g_w):
        """Along V = (V_W, V_b, V_K, V_beta): the forward derivative of z [B, N*A] and
        Hess(sum_b q_z[b] . z[b]) V in (W, b, K, beta); ``g_w`` = ``unit_vjp(q_z)[0]``."""
        V_W, V_b, V_K, V_beta = V
        dw = self._from_unit(V_W)
        dmix, hw, hb, hK, hbeta = tree_st_hvp(self._mix_cotangent(q_z), dw, V_b, V_K, V_beta, self.K, self.beta,
                                              self.obs, self.margins, self.t_near, self.tau, self.depth)
        g_W = self._from_unit(g_w)
        curvature = -(dw * (self.w * g_w).sum(-1, keepdims=True) + self.w * (dw * g_w).sum(-1, keepdims=True)) \
            / self.r - g_W * (self.w * V_W).sum(-1, keepdims=True) / self.r
        N, B, A = dmix.shape
        dz = (dmix * self.s_a[:, None]).transpose(1, 0, 2).reshape(B, N * A)
        return dz, (self._from_unit(hw) + curvature, hb, hK, hbeta)


def forest_forward_reference(trees, obs, tau: float):
    """``forest_forward`` as one autograd graph over every leaf (all tree arithmetic in
    float64): the reference ``TreeCore``'s kernels are tested against."""
    if not float(tau) > 0:
        raise ValueError(f"tree: tau must be > 0, got {tau}")
    first = trees[0]
    obs = obs.double()        # dtype policy: all tree arithmetic in float64
    margins = gate_margins(st_top_k(_stacked(trees, "W"), first.split_k), _stacked(trees, "b"), obs)
    leaf, nodes, sides = route(margins.detach(), first.depth)
    weight = st_leaf_weights(margins, tau, first.depth)                      # [N, B, L]
    squashed = torch.tanh(leaf_preactivations(st_top_k(_stacked(trees, "K"), first.leaf_k),
                                              _stacked(trees, "beta"), obs))
    N, B, L, A = squashed.shape
    mixed = torch.bmm(weight.reshape(N * B, 1, L), squashed.reshape(N * B, L, A)).reshape(N, B, A)
    action = _stacked(trees, "c_a").double()[:, None] + _stacked(trees, "s_a").double()[:, None] * mixed
    return action.to(first.K.dtype), leaf, nodes, sides


def _numpy(x):
    return x.detach().contiguous().numpy()


class TreeCore(torch.autograd.Function):
    """The routed leaf sum mix = sum_l weight_l tanh(K_l o + beta_l) of unit split vectors
    w [N,I,O], thresholds b [N,I], gains K [N,L,A,O], offsets beta [N,L,A] (float64) on obs
    [N,B,O]: returns (mix [N,B,A], leaf, nodes, sides). Its backward is ``TreeVJP``, itself
    differentiable once (TALO's Hessian-vector product)."""

    @staticmethod
    def forward(ctx, w, b, K, beta, obs, tau, depth):
        near = any(ctx.needs_input_grad[:4])   # the backward's arrays only where one will run
        obs_np = _numpy(obs)
        mix, margins, leaf, nodes, sides, _, t_near, g1 = tree_st_forward(
            _numpy(w), _numpy(b), _numpy(K), _numpy(beta), obs_np, int(depth), float(tau), near)
        ctx.save_for_backward(w, b, K, beta)
        ctx.cache = (obs_np, margins, leaf, nodes, sides, t_near, g1, float(tau), int(depth),
                     tuple(w.shape), tuple(K.shape))
        out = [torch.from_numpy(v) for v in (leaf, nodes, sides)]
        ctx.mark_non_differentiable(*out)
        return (torch.from_numpy(mix), *out)

    @staticmethod
    def backward(ctx, g_mix, *_):
        if g_mix is None:
            return (None,) * 7
        return (*TreeVJP.apply(g_mix, *ctx.saved_tensors, ctx.cache), None, None, None)


class TreeVJP(torch.autograd.Function):
    """grad of sum q . mix in (w, b, K, beta) (``tree_st_vjp``); its backward along a direction
    V of those shapes is the double backward (``tree_st_hvp``): d/dq = the forward
    derivative of mix along V, d/dtheta = Hess(q . mix) V. The parameters are inputs (the
    forward reads them through the cache) so that autograd routes those terms to them."""

    @staticmethod
    def forward(ctx, q, w, b, K, beta, cache):
        obs, _, leaf, nodes, sides, t_near, g1, _, _, shape_w, shape_K = cache
        q_np = _numpy(q.double())
        ctx.save_for_backward(K, beta)
        ctx.q, ctx.cache, ctx.q_dtype = q_np, cache, q.dtype
        gw, gb, gK, gbeta = tree_st_vjp(q_np, obs, leaf, nodes, sides, t_near, g1, shape_w, shape_K)
        return tuple(torch.from_numpy(g) for g in (gw, gb, gK, gbeta))

    @staticmethod
    @once_differentiable
    def backward(ctx, *V):
        K, beta = ctx.saved_tensors
        obs, margins, _, _, _, t_near, _, tau, depth, shape_w, shape_K = ctx.cache
        shapes = (shape_w, shape_w[:2], shape_K, shape_K[:3])
        V = [np.zeros(shape) if v is None else _numpy(v.double()) for v, shape in zip(V, shapes)]
        dmix, hw, hb, hK, hbeta = tree_st_hvp(ctx.q, *V, _numpy(K), _numpy(beta), obs, margins, t_near,
                                              tau, depth)
        return torch.from_numpy(dmix).to(ctx.q_dtype), *(torch.from_numpy(h) for h in (hw, hb, hK, hbeta)), None


class HardObliqueTree(nn.Module):
    """One carrier's hard oblique tree; hard forward, straight-through backward.
    With ``config.split_k``/``leaf_k`` the forward (and the exported arrays the
    actors run) uses the k largest weights of each split vector / leaf gain row
    (``st_top_k``); the parameters stay dense for the learner."""

    def __init__(self, obs_dim: int, act_dim: int = 3, depth: int | None = None, config: TreeConfig | None = None):
        super().__init__()
        cfg = config or TreeConfig()
        depth = cfg.depth if depth is None else depth
        if depth < 1 or obs_dim < 1 or act_dim < 1:
            raise ValueError(f"tree: need depth, obs_dim, act_dim >= 1, got {depth}, {obs_dim}, {act_dim}")
        self.obs_dim, self.act_dim, self.depth = obs_dim, act_dim, depth
        self.n_internal, self.n_leaves = 2**depth - 1, 2**depth
        W = torch.randn(self.n_internal, obs_dim)
        self.W = nn.Parameter(W / W.norm(dim=1, keepdim=True))  # random unit split vectors
        self.b = nn.Parameter(cfg.b_init_scale * torch.randn(self.n_internal))
        self.K = nn.Parameter(cfg.k_init_scale / math.sqrt(obs_dim) * torch.randn(self.n_leaves, act_dim, obs_dim))
        self.beta = nn.Parameter(torch.zeros(self.n_leaves, act_dim))
        self.log_std = nn.Parameter(torch.full((act_dim,), float(cfg.init_log_std)))
        self.register_buffer("c_a", torch.full((act_dim,), float(cfg.action_center)))
        self.register_buffer("s_a", torch.full((act_dim,), float(cfg.action_half_range)))
        if cfg.split_k < 0 or cfg.leaf_k < 0:
            raise ValueError(f"tree: split_k and leaf_k must be >= 0 (0 = dense), got {cfg.split_k}, {cfg.leaf_k}")
        self.split_k, self.leaf_k = int(cfg.split_k), int(cfg.leaf_k)

    def split_W(self):
        """The split vectors the tree routes with: k-sparse if split_k (straight-through)."""
        return st_top_k(self.W, self.split_k)

    def leaf_K(self):
        """The leaf gains the tree acts with: k-sparse rows if leaf_k (straight-through)."""
        return st_top_k(self.K, self.leaf_k)

    def gate_margins(self, obs):
        """w_k.o - b_k for every internal node, float64 [B, n_internal] (see dtype policy)."""
        return gate_margins(self.split_W()[None], self.b[None], obs[None])[0]

    def leaf_actions(self, obs):
        """c_a + s_a tanh(K_l o + beta_l) for every leaf, [B, n_leaves, act_dim] float64."""
        u = leaf_preactivations(self.leaf_K()[None], self.beta[None], obs[None])[0]
        return self.c_a.double() + self.s_a.double() * torch.tanh(u)

    def route(self, margins):
        """Hard routing (Eq. hard_gate): leaf [B], nodes [B,D], sides [B,D] (True = right)."""
        leaf, nodes, sides = route(margins[None], self.depth)
        return leaf[0], nodes[0], sides[0]

    def st_leaf_weights(self, margins, tau):
        """Path products of g^ST / 1 - g^ST, [B, n_leaves] float64; forward value = hard one-hot."""
        return st_leaf_weights(margins[None], tau, self.depth)[0]

    def forward(self, obs, tau: float = 1.0) -> TreeOutput:
        if obs.ndim != 2 or obs.shape[1] != self.obs_dim:
            raise ValueError(f"tree: obs must be [B,{self.obs_dim}], got {tuple(obs.shape)}")
        action, leaf, nodes, sides = forest_forward([self], obs[None], tau)
        return TreeOutput(action[0], leaf[0], nodes[0], sides[0])

    def export_arrays(self) -> dict[str, np.ndarray]:
        """The arrays actors run: W and K as the forward uses them (k-sparse where configured)."""
        value = {"W": self.split_W, "K": self.leaf_K}
        return {name: (value[name]() if name in value else getattr(self, name)).detach().cpu().numpy()
                .astype(np.float32) for name in PARAM_NAMES}

class TeamPolicy(nn.Module):
    """N independent hard trees (no parameter sharing); stacked action [B, N*act_dim]."""

    def __init__(self, n_agents: int, obs_dim: int, act_dim: int = 3, depth: int | None = None, config: TreeConfig | None = None):
        super().__init__()
        if n_agents < 1:
            raise ValueError(f"team: n_agents must be >= 1, got {n_agents}")
        self.n_agents, self.obs_dim, self.act_dim = n_agents, obs_dim, act_dim
        self.trees = nn.ModuleList(HardObliqueTree(obs_dim, act_dim, depth, config) for _ in range(n_agents))
        self.depth = self.trees[0].depth

    @property
    def log_std(self):
        """Stacked proposal log-std [N*act_dim] (differentiable)."""
        return torch.cat([tree.log_std for tree in self.trees])

    def forward(self, obs, tau: float = 1.0) -> TreeOutput:
        if obs.ndim != 3 or obs.shape[1:] != (self.n_agents, self.obs_dim):
            raise ValueError(f"team: obs must be [B,{self.n_agents},{self.obs_dim}], got {tuple(obs.shape)}")
        action, leaf, nodes, sides = forest_forward(self.trees, obs.transpose(0, 1), tau)
        B = obs.shape[0]
        return TreeOutput(action.transpose(0, 1).reshape(B, -1), leaf.T, nodes.transpose(0, 1),
                          sides.transpose(0, 1))

    def taped(self, obs, tau: float = 1.0) -> ForestTape:
        """The forward without a graph, keeping what its closed-form derivatives read
        (``ForestTape``; its ``action`` is ``forward``'s)."""
        if obs.ndim != 3 or obs.shape[1:] != (self.n_agents, self.obs_dim):
            raise ValueError(f"team: obs must be [B,{self.n_agents},{self.obs_dim}], got {tuple(obs.shape)}")
        if not float(tau) > 0:
            raise ValueError(f"tree: tau must be > 0, got {tau}")
        return ForestTape(self.trees, obs.transpose(0, 1), tau)

    def spec(self) -> ParamsSpec:
        return ParamsSpec(self.n_agents, self.obs_dim, self.act_dim, self.depth)

    def export_params(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {"format_version": np.asarray(FORMAT_VERSION, dtype=np.float32)}
        for i, tree in enumerate(self.trees):
            out.update({f"carrier_{i}/{k}": v for k, v in tree.export_arrays().items()})
        return out

    def load_params(self, params: Mapping[str, np.ndarray]) -> None:
        spec = validate_params(params)
        if spec != self.spec():
            raise InvalidParams(f"params have shape spec {spec}, this team is {self.spec()}")
        with torch.no_grad():
            for i, tree in enumerate(self.trees):
                for name in PARAM_NAMES:
                    target = getattr(tree, name)
                    target.copy_(torch.as_tensor(np.asarray(params[f"carrier_{i}/{name}"]), dtype=target.dtype))

    @classmethod
    def from_params(cls, params: Mapping[str, np.ndarray]) -> "TeamPolicy":
        spec = validate_params(params)
        team = cls(spec.n_agents, spec.obs_dim, spec.act_dim, spec.depth)
        team.load_params(params)
        return team


def policy_params_from_checkpoint(ckpt: Mapping) -> dict[str, np.ndarray]:
    """The flat numpy tree parameters (``TeamPolicy.export_params``) of a learner
    checkpoint, whatever its method: the TeamPolicy state dict is
    ``ckpt["method"]["policy"]`` (keys ``trees.{i}.W`` ...), and the shapes in it
    give the team size, observation size, action size and depth, and the run
    config stored with it (``ckpt["config"]``, TrainConfig JSON) the sparsity:
    the state holds the dense straight-through weights, so without
    ``algo.split_k`` / ``leaf_k`` a sparse run would export dense trees. The one
    path from a checkpoint to the parameters an actor, ``sage eval`` or a bundle runs."""
    state = ckpt.get("method", {}).get("policy") if isinstance(ckpt, Mapping) else None
    if not isinstance(state, Mapping) or "trees.0.W" not in state:
        raise ValueError("checkpoint holds no TeamPolicy state ('method'/'policy'/'trees.0.W')")
    n_agents = 1 + max(int(k.split(".")[1]) for k in state if k.startswith("trees."))
    W, K = state["trees.0.W"], state["trees.0.K"]
    depth = int(round(math.log2(W.shape[0] + 1)))
    algo = json.loads(ckpt["config"]).get("algo", {}) if isinstance(ckpt.get("config"), str) else {}
    tree_cfg = TreeConfig(depth=depth, split_k=int(algo.get("split_k", 0)), leaf_k=int(algo.get("leaf_k", 0)))
    policy = TeamPolicy(n_agents, int(W.shape[1]), act_dim=int(K.shape[1]), config=tree_cfg)
    policy.load_state_dict(state)
    return policy.export_params()
