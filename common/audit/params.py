"""Reading the flat tree parameters (``TeamPolicy.export_params``) for auditing.

The wire format is a flat ``dict[str, np.ndarray]`` with keys ``carrier_{i}/W``,
``carrier_{i}/b``, ``carrier_{i}/K``, ``carrier_{i}/beta`` and the action bounds
``carrier_{i}/c_a``, ``carrier_{i}/s_a`` (docs/interfaces.md, common/policy/tree.py).
This module only reads it; it never imports torch unless asked to open a
torch checkpoint.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.audit.config import AuditConfig
from common.audit.safe_npz import load_npz
from common.env.config import EnvConfig
from common.env.observations import OBS_FEATURE_NAMES, feature_units

_CARRIER_KEY = re.compile(r"^carrier_(\d+)/(.+)$")


class BadPolicyParams(ValueError):
    """The parameter dict does not describe a team of hard oblique trees."""


@dataclass(frozen=True)
class CarrierTree:
    """One carrier's hard oblique tree (Eqs. hard_gate, hard_tree_policy).

    Nodes are in heap order: children of ``k`` are ``2k+1`` (left, ``w.o <= b``)
    and ``2k+2`` (right, ``w.o > b``); leaf ``l`` is heap node ``n_internal + l``.
    """

    W: np.ndarray      # [n_internal, obs_dim], used normalized (||w_k|| = 1)
    b: np.ndarray      # [n_internal]
    K: np.ndarray      # [n_leaves, act_dim, obs_dim]
    beta: np.ndarray   # [n_leaves, act_dim]
    c_a: np.ndarray    # [act_dim] center of the action bounds
    s_a: np.ndarray    # [act_dim] half-range of the action bounds

    @property
    def n_internal(self) -> int:
        return self.W.shape[0]

    @property
    def n_leaves(self) -> int:
        return self.K.shape[0]

    @property
    def depth(self) -> int:
        return int(round(np.log2(self.n_leaves)))

    @property
    def obs_dim(self) -> int:
        return self.W.shape[1]

    @property
    def act_dim(self) -> int:
        return self.K.shape[1]

    def unit_W(self) -> np.ndarray:
        """Split directions w_k = W_k / ||W_k|| as used in Eq. (hard_gate)."""
        norms = np.linalg.norm(self.W, axis=1, keepdims=True)
        return self.W / np.maximum(norms, 1e-12)

    def bias_command(self) -> np.ndarray:
        """Leaf command at o = 0: c_a + s_a * tanh(beta_l), Eq. (hard_tree_policy). [n_leaves, act_dim]"""
        return self.c_a + self.s_a * np.tanh(self.beta)


def _validate(i: int, tree: CarrierTree) -> None:
    n_int, n_leaves = tree.W.shape[0], tree.K.shape[0]
    if tree.W.ndim != 2 or tree.K.ndim != 3 or tree.beta.ndim != 2:
        raise BadPolicyParams(f"carrier_{i}: W must be 2-D, K 3-D, beta 2-D "
                              f"(got {tree.W.shape}, {tree.K.shape}, {tree.beta.shape})")
    if n_leaves < 2 or n_leaves & (n_leaves - 1) or n_int != n_leaves - 1:
        raise BadPolicyParams(f"carrier_{i}: need n_leaves = 2^depth and n_internal = n_leaves - 1, "
                              f"got W {tree.W.shape}, K {tree.K.shape}")
    if tree.b.shape != (n_int,):
        raise BadPolicyParams(f"carrier_{i}: b shape {tree.b.shape} != ({n_int},)")
    if tree.K.shape[2] != tree.W.shape[1]:
        raise BadPolicyParams(f"carrier_{i}: K obs dim {tree.K.shape[2]} != W obs dim {tree.W.shape[1]}")
    act = tree.K.shape[1]
    if tree.beta.shape != (n_leaves, act):
        raise BadPolicyParams(f"carrier_{i}: beta shape {tree.beta.shape} != ({n_leaves}, {act})")
    for name in ("c_a", "s_a"):
        if getattr(tree, name).shape != (act,):
            raise BadPolicyParams(f"carrier_{i}: {name} shape {getattr(tree, name).shape} != ({act},)")
    for name in ("W", "b", "K", "beta", "c_a", "s_a"):
        if not np.all(np.isfinite(getattr(tree, name))):
            raise BadPolicyParams(f"carrier_{i}/{name} has NaN or Inf")


def split_carriers(params: dict) -> list[CarrierTree]:
    """Flat export dict -> one validated ``CarrierTree`` per carrier, in carrier order."""
    by_carrier: dict[int, dict[str, np.ndarray]] = {}
    for key, value in params.items():
        m = _CARRIER_KEY.match(key)
        if m:
            by_carrier.setdefault(int(m.group(1)), {})[m.group(2)] = np.asarray(value, dtype=np.float64)
    if not by_carrier:
        raise BadPolicyParams("no 'carrier_{i}/...' keys: not a TeamPolicy.export_params() dict "
                              f"(keys: {sorted(params)[:8]})")
    if sorted(by_carrier) != list(range(len(by_carrier))):
        raise BadPolicyParams(f"carrier indices must be 0..N-1, got {sorted(by_carrier)}")
    trees = []
    for i in range(len(by_carrier)):
        p = by_carrier[i]
        missing = [k for k in ("W", "b", "K", "beta", "c_a", "s_a") if k not in p]
        if missing:
            raise BadPolicyParams(f"carrier_{i} lacks {missing}")
        tree = CarrierTree(W=p["W"], b=p["b"], K=p["K"], beta=p["beta"],
                           c_a=p["c_a"].reshape(-1), s_a=p["s_a"].reshape(-1))
        _validate(i, tree)
        trees.append(tree)
    if len({t.obs_dim for t in trees}) != 1:
        raise BadPolicyParams("carriers disagree on obs_dim")
    return trees


def _find_flat_params(obj, depth: int = 0):
    """Depth-first search of a checkpoint for the flat export dict (has 'carrier_0/W')."""
    if isinstance(obj, dict):
        if "carrier_0/W" in obj:
            return obj
        if depth < 4:
            for value in obj.values():
                found = _find_flat_params(value, depth + 1)
                if found is not None:
                    return found
    return None


def _to_numpy(value):
    if hasattr(value, "detach"):  # torch tensor, only present when a checkpoint was loaded
        return value.detach().cpu().numpy()
    return np.asarray(value)


def load_params_file(path: str | Path) -> dict[str, np.ndarray]:
    """Flat policy params from a checkpoint (torch.save dict), an .npz (flat params or a
    decision-trace recording) or a .json file (flat params or a bundle's trees.json)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such policy file: {path}")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        raw = load_npz(path, AuditConfig().max_npz_bytes)   # headers checked before allocating
        prefix = "params::"  # a decision-trace recording embeds the params it ran (recording.py)
        if any(k.startswith(prefix) for k in raw):
            raw = {k[len(prefix):]: v for k, v in raw.items() if k.startswith(prefix)}
    elif suffix == ".json":
        with open(path) as f:
            raw = json.load(f)
        if "trees" in raw and "carrier_0/W" not in raw:  # a deployment bundle's trees.json
            raw = bundle_json_to_params(raw)
    else:
        import torch  # checkpoints only; keeps .npz/.json audits torch-free

        ckpt = torch.load(path, map_location="cpu", weights_only=True)
        raw = _find_flat_params(ckpt)
        if raw is None:
            from common.policy.tree_torch import policy_params_from_checkpoint

            try:
                raw = policy_params_from_checkpoint(ckpt)
            except ValueError as exc:
                raise BadPolicyParams(f"{path}: neither flat policy params ('carrier_0/W') nor a learner "
                                      f"checkpoint ({exc})") from None
    params = {k: _to_numpy(v) for k, v in raw.items()}
    split_carriers(params)  # validate early, with a clear message
    return params


def save_params_json(params: dict, path: str | Path) -> None:
    """Write a flat params dict as JSON (nested lists), readable by ``load_params_file``."""
    out = {k: np.asarray(v).tolist() for k, v in params.items()}
    with open(path, "w") as f:
        json.dump(out, f)


def bundle_json_to_params(doc: dict) -> dict[str, np.ndarray]:
    """The inverse of the bundle's human-readable trees.json (see common/audit/bundle.py)."""
    params: dict[str, np.ndarray] = {}
    for i, tree in enumerate(doc["trees"]):
        internal = sorted(tree["nodes"], key=lambda n: n["id"])
        leaves = sorted(tree["leaves"], key=lambda n: n["leaf"])
        params[f"carrier_{i}/W"] = np.array([n["w"] for n in internal], dtype=np.float64)
        params[f"carrier_{i}/b"] = np.array([n["b"] for n in internal], dtype=np.float64)
        params[f"carrier_{i}/K"] = np.array([lf["K"] for lf in leaves], dtype=np.float64)
        params[f"carrier_{i}/beta"] = np.array([lf["beta"] for lf in leaves], dtype=np.float64)
        params[f"carrier_{i}/c_a"] = np.array(tree["c_a"], dtype=np.float64)
        params[f"carrier_{i}/s_a"] = np.array(tree["s_a"], dtype=np.float64)
    return params


def feature_names(obs_dim: int, names: list[str] | None = None) -> list[str]:
    """The environment's observation feature names when they fit ``obs_dim``, else ``o[j]``."""
    names = OBS_FEATURE_NAMES if names is None else names
    if len(names) == obs_dim:
        return list(names)
    return [f"o[{j}]" for j in range(obs_dim)]


def feature_units_of(names: list[str], env: EnvConfig | None = None) -> dict[str, tuple[float, str]] | None:
    """(scale, unit) of each environment feature for readable predicates
    (``common.env.observations.feature_units`` of ``env``, default EnvConfig);
    None for names that are not the environment's."""
    if list(names) != OBS_FEATURE_NAMES:
        return None
    return feature_units(env or EnvConfig())
