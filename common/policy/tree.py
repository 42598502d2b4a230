"""Hard oblique decision-tree actors (Sec. III-B, Eqs. hard_gate, hard_tree_policy, st_gate).

One tree per carrier, no parameter sharing. Nodes are in heap order: root 0, the
children of k are 2k+1 (gate 0, "left", w.o <= b) and 2k+2 (gate 1, "right",
w.o > b); with depth D there are 2^D - 1 internal nodes and leaf l is heap node
(2^D - 1) + l.

    g_k(o) = 1[w_k.o > b_k],  w_k = W_k / ||W_k||                        # Eq. (hard_gate)
    a_nom(o) = c_a + s_a * tanh(K_l o + beta_l),  l = hard-routed leaf     # Eq. (hard_tree_policy)
    g_k^ST = sg(g_k - p_k) + p_k,  p_k = sigmoid((w_k.o - b_k) / tau)     # Eq. (st_gate)

Training forward: the leaf weight of leaf l is the product over its path of g^ST
(right) or 1 - g^ST (left); its forward value is exactly the hard one-hot (we
write g^ST as g + (p - sg(p)), which is exactly g in floating point, unlike
(g - p) + p), and its gradient reaches W and b through the path products. The
action is sum_l weight_l * (c_a + s_a tanh(K_l o + beta_l)), i.e. exactly the
hard leaf's action.

Dtype policy: parameters are stored in float32, but all tree arithmetic (gate
margins w.o - b, leaf controllers) runs in float64 in both the torch module and
the numpy twins, from the same float32 observations and parameters. Routing can
then disagree between the two only if |w.o - b| is at float64 rounding level
(~1e-15), whereas float32 margins flip routes within ~1e-7 of a threshold. The
torch action is returned in the parameter dtype (float32), the numpy one in
float64; they differ by float32 rounding only.

Parameters travel as a flat dict[str, np.ndarray] (`export_params`): keys
"carrier_{i}/{W,b,K,beta,log_std,c_a,s_a}" (float32) plus "format_version".
`log_std` is the per-carrier proposal spread (common/policy/proposal.py); it lives in
the tree so it travels with the tree parameters.

This module is numpy only (`tree_forward_np`, `team_forward_np` — a numba
kernel; its numpy reference is `reference.team_forward` in common/policy/reference.py —,
`validate_params`): actor processes never import torch. The torch classes
(`HardObliqueTree`, `TeamPolicy`) are in `common/policy/tree_torch.py`.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from common.policy.tree_kernels import team_forward_kernel

FORMAT_VERSION = 1
PARAM_NAMES = ("W", "b", "K", "beta", "log_std", "c_a", "s_a")


@dataclass(frozen=True)
class TreeConfig:
    depth: int = 4                 # 2^depth leaves
    b_init_scale: float = 0.1      # thresholds b ~ N(0, b_init_scale^2)
    k_init_scale: float = 0.1      # K ~ N(0, (k_init_scale / sqrt(obs_dim))^2): weak random controller
    init_log_std: float = -0.5     # proposal spread in pre-tanh space (sigma ~ 0.61)
    action_center: float = 0.0     # c_a (action box [-1, 1])
    action_half_range: float = 1.0  # s_a
    # Sparse oblique splits (ICCT-style readability): each split vector w_k has at
    # most split_k non-zero features (0 = dense, all obs_dim), each leaf gain row K_l[a]
    # at most leaf_k (0 = dense): the k largest |.| of the learner's dense weights,
    # straight-through (common/policy/tree_torch.py), so which features are kept can change.
    split_k: int = 0
    leaf_k: int = 0


class TreeOutput(NamedTuple):
    """Tree: action [B,A], leaf [B], nodes/sides [B,D]. Team: action [B,N*A], leaf [B,N], nodes/sides [B,N,D]."""

    action: object
    leaf: object
    nodes: object
    sides: object


class ParamsSpec(NamedTuple):
    n_agents: int
    obs_dim: int
    act_dim: int
    depth: int


class InvalidParams(ValueError):
    """Exported tree parameters that are missing, mis-shaped, non-float or non-finite."""


# ----------------------------------------------------------------------------- parameter dicts


def _depth_of(n_internal: int) -> int:
    depth = int(round(math.log2(n_internal + 1))) if n_internal > 0 else 0
    if depth < 1 or 2**depth - 1 != n_internal:
        raise InvalidParams(f"W has {n_internal} rows; expected 2^depth - 1 internal nodes with depth >= 1")
    return depth


def _expected_shapes(obs_dim: int, act_dim: int, depth: int) -> dict[str, tuple[int, ...]]:
    n_internal, n_leaves = 2**depth - 1, 2**depth
    return {
        "W": (n_internal, obs_dim),
        "b": (n_internal,),
        "K": (n_leaves, act_dim, obs_dim),
        "beta": (n_leaves, act_dim),
        "log_std": (act_dim,),
        "c_a": (act_dim,),
        "s_a": (act_dim,),
    }


class ValidatedParams(dict):
    """A parameter dict that passed ``validate_params`` once, with its ``spec``:
    the actor checks each broadcast at adoption and then runs it every step, so
    the per-step forward skips the check (it was 40% of ``propose``). Treat as
    read-only: changing an array after validation is not re-checked."""

    def __init__(self, params: Mapping[str, np.ndarray]):
        super().__init__(params)
        self.spec = validate_params(params)
        self.stacked = stack_team_arrays(self, self.spec)   # what the forward kernel reads, built once
        self.log_std = _stack_log_std(self, self.spec)      # the proposal's, likewise


def validate_params(params: Mapping[str, np.ndarray]) -> ParamsSpec:
    """Check an exported parameter dict; returns its shape spec or raises InvalidParams."""
    if isinstance(params, ValidatedParams):
        return params.spec
    if not isinstance(params, Mapping):
        raise InvalidParams(f"params must be a mapping, got {type(params).__name__}")
    if "format_version" not in params:
        raise InvalidParams("params lack 'format_version'")
    version = np.asarray(params["format_version"])
    if version.size != 1 or version.dtype.kind not in "iuf" or float(version.reshape(())) != FORMAT_VERSION:
        raise InvalidParams(f"params format_version {version!r} is not supported (expected {FORMAT_VERSION})")
    carriers: dict[int, dict[str, np.ndarray]] = {}
    for key, value in params.items():
        if key == "format_version":
            continue
        head, _, name = key.partition("/")
        if not head.startswith("carrier_") or not head[8:].isdigit() or name not in PARAM_NAMES:
            raise InvalidParams(f"unknown params key {key!r} (expected 'carrier_<i>/<{'|'.join(PARAM_NAMES)}>')")
        carriers.setdefault(int(head[8:]), {})[name] = value
    if not carriers or sorted(carriers) != list(range(len(carriers))):
        raise InvalidParams(f"carrier indices must be 0..N-1, got {sorted(carriers)}")
    spec = None
    for i in range(len(carriers)):
        arrays = carriers[i]
        missing = [n for n in PARAM_NAMES if n not in arrays]
        if missing:
            raise InvalidParams(f"carrier_{i} lacks {missing}")
        for name in PARAM_NAMES:
            arr = np.asarray(arrays[name])
            if arr.dtype.kind != "f":
                raise InvalidParams(f"carrier_{i}/{name} must be a float array, got dtype {arr.dtype}")
            if not np.all(np.isfinite(arr)):
                raise InvalidParams(f"carrier_{i}/{name} contains NaN/Inf")
        W, K = np.asarray(arrays["W"]), np.asarray(arrays["K"])
        if W.ndim != 2 or K.ndim != 3:
            raise InvalidParams(f"carrier_{i}: W must be 2-D and K 3-D, got {W.shape} and {K.shape}")
        this = ParamsSpec(len(carriers), W.shape[1], K.shape[1], _depth_of(W.shape[0]))
        for name, shape in _expected_shapes(this.obs_dim, this.act_dim, this.depth).items():
            if np.shape(arrays[name]) != shape:
                raise InvalidParams(f"carrier_{i}/{name} has shape {np.shape(arrays[name])}, expected {shape}")
        if spec is not None and this != spec:
            raise InvalidParams(f"carrier_{i} has shape spec {this}, carrier_0 has {spec}")
        if np.any(np.linalg.norm(W, axis=1) == 0):
            raise InvalidParams(f"carrier_{i}/W has a zero row (split vectors are normalized)")
        if np.any(np.asarray(arrays["s_a"]) <= 0):
            raise InvalidParams(f"carrier_{i}/s_a must be > 0")
        spec = this
    return spec


def carrier_params(params: Mapping[str, np.ndarray], i: int) -> dict[str, np.ndarray]:
    """The arrays of carrier i without the 'carrier_i/' prefix."""
    return {name: params[f"carrier_{i}/{name}"] for name in PARAM_NAMES}


def team_log_std(params: Mapping[str, np.ndarray]) -> np.ndarray:
    """Stacked proposal log-std [N*A] (float64) from an exported dict (``ValidatedParams``
    hold it stacked once; treat the result as read-only)."""
    if isinstance(params, ValidatedParams):
        return params.log_std
    return _stack_log_std(params, validate_params(params))


def _stack_log_std(params: Mapping[str, np.ndarray], spec: ParamsSpec) -> np.ndarray:
    return np.concatenate([np.asarray(params[f"carrier_{i}/log_std"], np.float64) for i in range(spec.n_agents)])


# ----------------------------------------------------------------------------- numpy twins (actors)


def _route_np(margins: np.ndarray):
    """Hard routing from float64 gate margins [B, 2^D - 1] -> (leaf [B], nodes [B,D], sides [B,D])."""
    B, n_internal = margins.shape
    depth = _depth_of(n_internal)
    hard = margins > 0  # Eq. (hard_gate): right iff w.o > b
    rows = np.arange(B)
    node = np.zeros(B, dtype=np.int64)
    nodes = np.empty((B, depth), dtype=np.int64)
    sides = np.empty((B, depth), dtype=bool)
    for level in range(depth):
        side = hard[rows, node]
        nodes[:, level], sides[:, level] = node, side
        node = 2 * node + 1 + side
    return node - n_internal, nodes, sides


def tree_forward_np(params_i: Mapping[str, np.ndarray], obs: np.ndarray):
    """One carrier's hard tree in numpy: obs [B,obs_dim] -> (action [B,A] f64, leaf [B], nodes [B,D], sides [B,D])."""
    obs = np.asarray(obs)
    W = np.asarray(params_i["W"], dtype=np.float64)
    if obs.ndim != 2 or obs.shape[1] != W.shape[1]:
        raise ValueError(f"tree: obs must be [B,{W.shape[1]}], got {obs.shape}")
    obs64 = obs.astype(np.float64)
    w = W / np.linalg.norm(W, axis=1, keepdims=True)
    margins = obs64 @ w.T - np.asarray(params_i["b"], dtype=np.float64)
    leaf, nodes, sides = _route_np(margins)
    K = np.asarray(params_i["K"], dtype=np.float64)[leaf]
    u = np.einsum("bao,bo->ba", K, obs64) + np.asarray(params_i["beta"], dtype=np.float64)[leaf]
    c_a = np.asarray(params_i["c_a"], dtype=np.float64)
    s_a = np.asarray(params_i["s_a"], dtype=np.float64)
    return c_a + s_a * np.tanh(u), leaf, nodes, sides


def stack_team_arrays(params: Mapping[str, np.ndarray], spec: ParamsSpec) -> tuple:
    """The carriers' arrays stacked as the forward kernel reads them, float64 and
    contiguous: unit split vectors w [N,2^D-1,O], b, K, beta, c_a, s_a."""
    def stack(name):
        return np.ascontiguousarray(np.stack([np.asarray(params[f"carrier_{i}/{name}"], dtype=np.float64)
                                              for i in range(spec.n_agents)]))

    W = stack("W")
    w = np.ascontiguousarray(W / np.linalg.norm(W, axis=2, keepdims=True))
    return w, stack("b"), stack("K"), stack("beta"), stack("c_a"), stack("s_a")


def _team_inputs(params: Mapping[str, np.ndarray], obs: np.ndarray) -> tuple[ParamsSpec, np.ndarray]:
    spec = validate_params(params)
    obs = np.asarray(obs)
    if obs.ndim != 3 or obs.shape[1:] != (spec.n_agents, spec.obs_dim):
        raise ValueError(f"team: obs must be [B,{spec.n_agents},{spec.obs_dim}], got {obs.shape}")
    return spec, obs


def team_forward_np(params: Mapping[str, np.ndarray], obs: np.ndarray):
    """All carriers: obs [B,N,obs_dim] -> (a_st [B,N*A], leaves [B,N], nodes [B,N,D], sides [B,N,D]).
    The compiled kernel (common/policy/tree_kernels.py); ``reference.team_forward`` is its numpy twin."""
    spec, obs = _team_inputs(params, obs)
    stacked = params.stacked if isinstance(params, ValidatedParams) else stack_team_arrays(params, spec)
    return team_forward_kernel(np.ascontiguousarray(obs, dtype=np.float64), *stacked, spec.depth)
