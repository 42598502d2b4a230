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

import hashlib
import importlib
import importlib.util
import json
import math
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


RUNTIME_FILE = "bundle_runtime.py"
MAX_TREES_JSON_BYTES = 64 * 1024 * 1024   # a depth-8 team is ~10 MB of JSON


def code_files(directory: str) -> list[str]:
    """The bundle's python files, relative paths: the runtime and the QP package."""
    pkg = os.path.join(directory, QP_PACKAGE)
    names = sorted(n for n in os.listdir(pkg) if n.endswith(".py")) if os.path.isdir(pkg) else []
    return [RUNTIME_FILE] + [f"{QP_PACKAGE}/{n}" for n in names]


def _sha256(path: str) -> str:
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def _check_code(directory: str, doc: dict) -> None:
    """Every python file of the bundle is the one exported, byte for byte
    (``trees.json["code_sha256"]``): none missing, none added, none changed."""
    want = doc.get("code_sha256")
    if not isinstance(want, dict) or not want:
        raise ValueError(f"{directory}: trees.json lists no code hashes (exported by an older SAGE?); re-export it")
    have = code_files(directory)
    if sorted(have) != sorted(want):
        raise ValueError(f"{directory}: python files {sorted(set(have) ^ set(want))} differ from the exported set")
    for rel in have:
        if _sha256(os.path.join(directory, rel)) != want[rel]:
            raise ValueError(f"{directory}: {rel} differs from the exported file (content hash mismatch)")


def _finite_array(directory: str, what: str, value, ndim: int) -> np.ndarray:
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{directory}: {what} is not a numeric array") from None
    if a.ndim != ndim:
        raise ValueError(f"{directory}: {what} has {a.ndim} dimensions, expected {ndim}")
    if not np.isfinite(a).all():
        raise ValueError(f"{directory}: {what} holds NaN or Inf")
    return a


def _project_qp():
    """The exact CBF-QP of the SAGE installation this file belongs to, when it is
    the project's own ``common.audit.bundle_runtime`` (None for a bundle's copy)."""
    if __name__ != "common.audit.bundle_runtime":
        return None
    return importlib.import_module("common.shield.qp")


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
        """A bundle's trees, checked: every weight finite, shapes of one complete
        tree per carrier, and its python files the exported ones (content hashes
        in trees.json). Loaded by SAGE itself (``common.audit.bundle_runtime``),
        the bundle's python is never imported: the project's own QP runs. Only
        the bundle's own copy of this file, run standalone, imports its
        ``sage_qp``, after the same hash check."""
        path = os.path.join(directory, TREES_FILE)
        if os.path.getsize(path) > MAX_TREES_JSON_BYTES:
            raise ValueError(f"{path}: larger than {MAX_TREES_JSON_BYTES} bytes, not a bundle's trees")
        with open(path) as f:
            doc = json.load(f, parse_constant=lambda c: math.nan)   # NaN/Infinity literals: refused below
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
            raise ValueError(f"{directory}: unknown bundle format {got!r}, expected {FORMAT!r}")
        _check_code(directory, doc)
        try:
            trees = [cls._tree(directory, i, t) for i, t in enumerate(doc["trees"])]
            names = [str(n) for n in doc["feature_names"]]
        except (KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"{directory}: trees.json is not a bundle's trees ({type(exc).__name__}: {exc})") from None
        if not trees or any(t.w.shape[1] != len(names) or t.K.shape[1:] != trees[0].K.shape[1:] for t in trees):
            raise ValueError(f"{directory}: trees and feature names disagree in size")
        meta = {k: v for k, v in doc.items() if k != "trees"}
        qp = _project_qp() or _load_qp(directory)
        return cls(trees, names, qp, meta)

    @staticmethod
    def _tree(directory: str, i: int, t: dict) -> BundleTree:
        nodes = sorted(t["nodes"], key=lambda n: n["id"])
        leaves = sorted(t["leaves"], key=lambda n: n["leaf"])
        what = f"carrier {i}"
        w = _finite_array(directory, f"{what} split vectors w", [n["w"] for n in nodes], 2)
        b = _finite_array(directory, f"{what} thresholds b", [n["b"] for n in nodes], 1)
        K = _finite_array(directory, f"{what} leaf gains K", [lf["K"] for lf in leaves], 3)
        beta = _finite_array(directory, f"{what} leaf biases beta", [lf["beta"] for lf in leaves], 2)
        c_a = _finite_array(directory, f"{what} c_a", t["c_a"], 1)
        s_a = _finite_array(directory, f"{what} s_a", t["s_a"], 1)
        n_leaves, act_dim = K.shape[0], K.shape[1]
        depth = n_leaves.bit_length() - 1
        if n_leaves < 2 or n_leaves != 2 ** depth or w.shape[0] != n_leaves - 1 or b.shape[0] != n_leaves - 1 \
                or K.shape[2] != w.shape[1] or beta.shape != (n_leaves, act_dim) or c_a.shape != (act_dim,) \
                or s_a.shape != (act_dim,):
            raise ValueError(f"{directory}: {what} is not a complete tree (w {w.shape}, K {K.shape})")
        return BundleTree(w=w, b=b, K=K, beta=beta, c_a=c_a, s_a=s_a)

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
