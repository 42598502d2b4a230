"""Standalone SAGE deployment runtime: hard-tree actors + exact joint CBF-QP.

This file is copied verbatim into every deployment bundle (``sage export-bundle``)
and must import only numpy and the bundle's own copy of the QP code (the
``sage_qp`` package next to ``trees.json``); no torch, no Zenoh, no project package.

Deterministic deployment, per control step:
  1. each carrier's hard oblique tree routes its own observation root-to-leaf,
     g_k(o) = [w_k . o > b_k]  (Eq. hard_gate), and emits the leaf command
     a_nom = c_a + s_a * tanh(K_l o + beta_l)  (Eq. hard_tree_policy);
  2. a human-occupied slot's block is replaced by the measured human action and
     held fixed;
  3. the stacked proposal is projected by the exact joint CBF-QP
     argmin 1/2 ||a~ - a||^2 s.t. C a~ >= c, a~ in [-1, 1]^d  (Eq. qpshield).

API::

    bundle = Bundle.load("bundle_dir")
    a_exec, traces = bundle.act(obs, (C, c, row_mask), fixed_mask=None, human_action=None)

``obs`` is [N, obs_dim] (one step) or [B, N, obs_dim]; ``C`` [(B,) M, 3N], ``c`` and
``row_mask`` [(B,) M]. ``a_exec`` has shape [(B,) 3N]; ``traces`` holds the per-carrier
leaf, node ids and sides of the root-to-leaf predicate sequence, the nominal
command ``a_st``, the QP's active rows, status and correction norm.
"""
from __future__ import annotations

import importlib.util
import json
import os
import sys
from dataclasses import dataclass

import numpy as np

TREES_FILE = "trees.json"
QP_PACKAGE = "sage_qp"
FORMAT = "sage-bundle/1"


@dataclass(frozen=True)
class BundleTree:
    w: np.ndarray      # [n_internal, obs_dim] unit split directions
    b: np.ndarray      # [n_internal]
    K: np.ndarray      # [n_leaves, act_dim, obs_dim]
    beta: np.ndarray   # [n_leaves, act_dim]
    c_a: np.ndarray    # [act_dim]
    s_a: np.ndarray    # [act_dim]

    @property
    def depth(self) -> int:
        return int(round(np.log2(self.K.shape[0])))

    def forward(self, obs: np.ndarray):
        """obs [B, obs_dim] -> (action [B, act_dim], leaf [B], nodes [B, depth], sides [B, depth])."""
        B = obs.shape[0]
        node = np.zeros(B, dtype=np.int64)
        nodes = np.empty((B, self.depth), dtype=np.int64)
        sides = np.empty((B, self.depth), dtype=bool)
        for d in range(self.depth):
            nodes[:, d] = node
            right = np.einsum("bj,bj->b", self.w[node], obs) > self.b[node]  # Eq. (hard_gate)
            sides[:, d] = right
            node = 2 * node + 1 + right
        leaf = node - self.w.shape[0]
        pre = np.einsum("baj,bj->ba", self.K[leaf], obs) + self.beta[leaf]
        return self.c_a + self.s_a * np.tanh(pre), leaf, nodes, sides  # Eq. (hard_tree_policy)


def _load_qp(directory: str):
    """Import the bundle's own copy of the exact CBF-QP (package ``sage_qp``) under a private name."""
    pkg = os.path.abspath(os.path.join(directory, QP_PACKAGE))
    init = os.path.join(pkg, "__init__.py")
    if not os.path.exists(init):
        raise FileNotFoundError(f"bundle {directory!r} lacks {QP_PACKAGE}/__init__.py")
    name = "sage_bundle_qp_" + "".join(ch if ch.isalnum() else "_" for ch in pkg)
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, init, submodule_search_locations=[pkg])
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # relative imports and dataclasses look the package up here
    spec.loader.exec_module(module)
    return module


class Bundle:
    """Loaded deployment bundle: trees + exact joint CBF-QP."""

    def __init__(self, trees: list[BundleTree], feature_names: list[str], qp_module, meta: dict):
        self.trees = trees
        self.feature_names = feature_names
        self.qp = qp_module
        self.meta = meta
        self.n_agents = len(trees)
        self.act_dim = trees[0].K.shape[1]
        self.obs_dim = trees[0].w.shape[1]

    @classmethod
    def load(cls, directory: str) -> "Bundle":
        with open(os.path.join(directory, TREES_FILE)) as f:
            doc = json.load(f)
        if doc.get("format") != FORMAT:
            raise ValueError(f"{directory}: unknown bundle format {doc.get('format')!r}, expected {FORMAT!r}")
        trees = []
        for t in doc["trees"]:
            nodes = sorted(t["nodes"], key=lambda n: n["id"])
            leaves = sorted(t["leaves"], key=lambda n: n["leaf"])
            trees.append(BundleTree(
                w=np.array([n["w"] for n in nodes], dtype=np.float64),
                b=np.array([n["b"] for n in nodes], dtype=np.float64),
                K=np.array([lf["K"] for lf in leaves], dtype=np.float64),
                beta=np.array([lf["beta"] for lf in leaves], dtype=np.float64),
                c_a=np.array(t["c_a"], dtype=np.float64),
                s_a=np.array(t["s_a"], dtype=np.float64)))
        meta = {k: v for k, v in doc.items() if k != "trees"}
        return cls(trees, list(doc["feature_names"]), _load_qp(directory), meta)

    def nominal(self, obs: np.ndarray):
        """Stacked nominal command a_st [B, N*act_dim] and per-carrier routes."""
        outs = [tree.forward(obs[:, i]) for i, tree in enumerate(self.trees)]
        a_st = np.concatenate([o[0] for o in outs], axis=1)
        leaves = np.stack([o[1] for o in outs], axis=1)
        nodes = np.stack([o[2] for o in outs], axis=1)
        sides = np.stack([o[3] for o in outs], axis=1)
        return a_st, leaves, nodes, sides

    def act(self, observations, rows, fixed_mask=None, human_action=None):
        """Executed (CBF-QP-filtered) actions and decision traces; see the module doc."""
        obs = np.asarray(observations, dtype=np.float64)
        single = obs.ndim == 2
        if single:
            obs = obs[None]
        if obs.ndim != 3 or obs.shape[1:] != (self.n_agents, self.obs_dim):
            raise ValueError(f"observations must be [N, obs_dim] or [B, N, obs_dim] with N={self.n_agents}, "
                             f"obs_dim={self.obs_dim}; got {np.shape(observations)}")
        if not np.all(np.isfinite(obs)):
            raise ValueError("observations contain NaN or Inf")
        C, c, row_mask = (None if r is None else np.asarray(r) for r in rows)
        if single:
            C, c = C[None], c[None]
            row_mask = None if row_mask is None else row_mask[None]
        B, d = obs.shape[0], self.n_agents * self.act_dim
        a_st, leaves, nodes, sides = self.nominal(obs)
        a_prop = a_st.copy()
        fixed = None
        if fixed_mask is not None:
            fixed = np.broadcast_to(np.asarray(fixed_mask, dtype=bool), (B, d))
            if fixed.any():
                if human_action is None:
                    raise ValueError("fixed_mask marks a human block but human_action is None")
                human = np.broadcast_to(np.asarray(human_action, dtype=np.float64), (B, d))
                a_prop = np.where(fixed, human, a_prop)  # the human block is exogenous (Sec. III-B)
        result = self.qp.solve_cbf_qp(a_prop, C, c, row_mask, fixed)  # Eq. (qpshield)
        traces = {"a_st": a_st, "a_prop": a_prop, "leaf": leaves, "nodes": nodes, "sides": sides,
                  "active": np.asarray(result.active), "status": np.asarray(result.status),
                  "correction_norm": np.asarray(result.correction_norm)}
        a_exec = np.asarray(result.a_exec)
        if single:
            return a_exec[0], {k: v[0] for k, v in traces.items()}
        return a_exec, traces
