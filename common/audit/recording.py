"""Decision traces of evaluation runs (Sec. IV-C): recording format and recorder.

A ``Recording`` holds, per control step and carrier, the root-to-leaf predicate
sequence (node ids and sides), the leaf, the nominal command a_st (Eq.
hard_tree_policy), the executed command (after the exact CBF-QP, Eq. qpshield),
the QP's active rows, plus route progress, payload pose and episode index. It
also keeps the observations, the safety rows and the flat policy params so
that decisions can be re-drawn and re-executed later (the deployment bundle
test replays them). Stored as a compressed .npz with no pickled objects;
metadata is one JSON string.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.audit.config import AuditConfig
from common.audit.params import feature_names
from common.audit.safe_npz import load_npz
from common.evaluation.deployment import evaluate_policy

RECORDING_VERSION = 1
_PARAM_PREFIX = "params::"


@dataclass
class Recording:
    """Steps of finished episodes, concatenated; S steps, N carriers, M rows, d = 3N."""

    episode: np.ndarray       # [S] int episode index (0..E-1)
    t: np.ndarray             # [S] int step within the episode
    obs: np.ndarray           # [S, N, obs_dim] observations the trees saw
    nodes: np.ndarray         # [S, N, depth] node ids on the root-to-leaf route
    sides: np.ndarray         # [S, N, depth] True = right (w.o > b)
    leaf: np.ndarray          # [S, N] leaf index
    a_st: np.ndarray          # [S, d] nominal tree command
    a_exec: np.ndarray        # [S, d] executed command
    active: np.ndarray        # [S, M] QP rows active at the solution
    progress: np.ndarray      # [S] route progress in [0, 1] at the observation
    payload_pose: np.ndarray  # [S, 3] payload (x, y, yaw) at the observation
    C: np.ndarray             # [S, M, d] safety rows C a >= c
    c: np.ndarray             # [S, M]
    row_mask: np.ndarray      # [S, M]
    fixed_mask: np.ndarray    # [S, d] human-held action components
    human_action: np.ndarray  # [S, d]
    params: dict = field(default_factory=dict)  # flat policy params used
    meta: dict = field(default_factory=dict)    # scenario, seed, shielded, feature names, episode metrics

    _ARRAYS = ("episode", "t", "obs", "nodes", "sides", "leaf", "a_st", "a_exec", "active", "progress",
               "payload_pose", "C", "c", "row_mask", "fixed_mask", "human_action")

    def __post_init__(self) -> None:
        S = len(self.episode)
        for name in self._ARRAYS:
            if len(getattr(self, name)) != S:
                raise ValueError(f"Recording.{name} has {len(getattr(self, name))} steps, episode has {S}")

    @property
    def n_steps(self) -> int:
        return len(self.episode)

    @property
    def n_agents(self) -> int:
        return self.leaf.shape[1]

    @property
    def n_episodes(self) -> int:
        return int(len(np.unique(self.episode)))

    def select(self, mask: np.ndarray) -> "Recording":
        kw = {n: getattr(self, n)[mask] for n in self._ARRAYS}
        return Recording(**kw, params=self.params, meta=self.meta)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"recordings are .npz files, got {path}")
        arrays = {n: np.asarray(getattr(self, n)) for n in self._ARRAYS}
        arrays.update({_PARAM_PREFIX + k: np.asarray(v) for k, v in self.params.items()})
        meta = dict(self.meta, recording_version=RECORDING_VERSION)
        arrays["meta_json"] = np.array(json.dumps(meta))
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path, max_bytes: int = AuditConfig().max_npz_bytes) -> "Recording":
        """A recording file, as data: its arrays within ``max_bytes`` (checked on
        the npy headers before anything is allocated), then every array's shape,
        dtype, finiteness and range checked (``check``); a ``ValueError`` naming
        the file otherwise."""
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"no such recording: {path}")
        data = load_npz(path, max_bytes)
        missing = [n for n in cls._ARRAYS + ("meta_json",) if n not in data]
        if missing:
            raise ValueError(f"{path} is not a SAGE recording (missing {missing})")
        kw = {n: data[n] for n in cls._ARRAYS}
        params = {k[len(_PARAM_PREFIX):]: v for k, v in data.items() if k.startswith(_PARAM_PREFIX)}
        meta = json.loads(str(data["meta_json"]))
        if not isinstance(meta, dict) or meta.get("recording_version") != RECORDING_VERSION:
            got = meta.get("recording_version") if isinstance(meta, dict) else None
            raise ValueError(f"{path}: recording version {got} != {RECORDING_VERSION}")
        try:
            rec = cls(**kw, params=params, meta=meta)
            rec.check()
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
        return rec

    def check(self) -> None:
        """Shapes that agree (S steps, N carriers, depth D, M rows, d = 3N), integer
        ids, finite floats, and leaves/nodes inside a depth-D tree."""
        S = self.n_steps
        if np.ndim(self.leaf) != 2 or np.ndim(self.nodes) != 3 or np.ndim(self.obs) != 3:
            raise ValueError(f"leaf {np.shape(self.leaf)}, nodes {np.shape(self.nodes)}, obs {np.shape(self.obs)}: "
                             "expected [S, N], [S, N, D], [S, N, obs_dim]")
        N, D = self.leaf.shape[1], self.nodes.shape[2]
        M = np.shape(self.active)[1] if np.ndim(self.active) == 2 else -1
        d = 3 * N
        want = {"episode": (S,), "t": (S,), "obs": (S, N, self.obs.shape[2]), "nodes": (S, N, D),
                "sides": (S, N, D), "leaf": (S, N), "a_st": (S, d), "a_exec": (S, d), "active": (S, M),
                "progress": (S,), "payload_pose": (S, 3), "C": (S, M, d), "c": (S, M), "row_mask": (S, M),
                "fixed_mask": (S, d), "human_action": (S, d)}
        for name, shape in want.items():
            a = getattr(self, name)
            if a.shape != shape:
                raise ValueError(f"{name} has shape {a.shape}, expected {shape}")
            kind = a.dtype.kind
            if name in ("episode", "t", "nodes", "leaf") and kind not in "iu":
                raise ValueError(f"{name} has dtype {a.dtype}, expected integers")
            if name in ("sides", "active", "row_mask", "fixed_mask") and kind != "b":
                raise ValueError(f"{name} has dtype {a.dtype}, expected bool")
            if kind not in "iubf":
                raise ValueError(f"{name} has dtype {a.dtype}, expected numbers")
            if kind == "f" and not np.isfinite(a).all():
                raise ValueError(f"{name} holds NaN or Inf")
        if D < 1 or D > 16:
            raise ValueError(f"tree depth {D} outside 1..16")
        for name, hi in (("leaf", 2 ** D), ("nodes", 2 ** D - 1)):
            a = getattr(self, name)
            if a.size and (a.min() < 0 or a.max() >= hi):
                raise ValueError(f"{name} ids outside 0..{hi - 1} (tree depth {D}): "
                                 f"{int(a.min())}..{int(a.max())}")
        for name in ("episode", "t"):
            a = getattr(self, name)
            if a.size and a.min() < 0:
                raise ValueError(f"{name} holds negative values")


def save(recording: Recording, path: str | Path) -> Path:
    return recording.save(path)


def load(path: str | Path) -> Recording:
    return Recording.load(path)


class Recorder:
    """Collects a ``Recording`` from the deployment loop
    (``common.evaluation.deployment.evaluate_policy(..., recorder=Recorder())``):
    every live step of each env's first episode, and that episode's metrics."""

    def __init__(self) -> None:
        self._steps: dict[str, list] = {n: [] for n in Recording._ARRAYS}
        self._t: np.ndarray | None = None
        self._metrics: dict[int, dict] = {}
        self._env = None
        self._goal_xy: np.ndarray | None = None

    def on_step(self, env, out, rows, decision, a_exec, active, live) -> None:
        if self._env is None:
            self._env = env
            self._goal_xy = np.asarray(env.goal_xy, np.float64).copy()  # goals of the first episodes
            # and their layouts' walls [K,W,5] (every episode in a layout of its own)
            self._walls = np.asarray(getattr(env, "walls_array", np.zeros((env.K, 0, 5))), np.float64).copy()
            self._t = np.zeros(env.K, dtype=np.int64)
        step = {"episode": np.arange(env.K), "t": self._t, "obs": out["obs"], "nodes": decision["nodes"],
                "sides": decision["sides"], "leaf": decision["leaf"], "a_st": decision["a_tree"],
                "a_exec": a_exec, "active": active, "progress": out["progress"], "payload_pose": payload_pose(env),
                "C": rows.C, "c": rows.c, "row_mask": rows.row_mask,
                "fixed_mask": np.asarray(rows.fixed_mask, dtype=bool), "human_action": out["human_action"]}
        for name in Recording._ARRAYS:
            self._steps[name].append(np.asarray(step[name])[live])
        self._t = self._t + 1

    def on_episode(self, k: int, metrics: dict) -> None:
        self._metrics[k] = _jsonable(metrics)

    def recording(self, params: dict, env_cfg, seed: int, shielded: bool) -> Recording:
        if self._env is None:
            raise ValueError("nothing was recorded")
        env, episodes = self._env, self._env.K
        arrays = {n: np.concatenate(v) for n, v in self._steps.items()}
        arrays["leaf"] = arrays["leaf"].astype(np.int16)
        arrays["nodes"] = arrays["nodes"].astype(np.int16)
        order = np.lexsort((arrays["t"], arrays["episode"]))  # episode-major
        arrays = {n: v[order] for n, v in arrays.items()}
        meta = {"scenario": getattr(env_cfg, "scenario", None), "seed": seed, "shielded": shielded,
                "episodes": episodes, "unfinished": episodes - len(self._metrics),
                "episode_metrics": [self._metrics.get(k) for k in range(episodes)],
                "feature_names": feature_names(env.obs_dim), "goal_xy": self._goal_xy.tolist(),
                "walls": self._walls.tolist()}   # [episode][wall] = (cx, cy, hx, hy, yaw)
        return Recording(**arrays, params={k: np.asarray(v) for k, v in params.items()}, meta=meta)


def record_episodes(params: dict, env_cfg, episodes: int, seed: int, shielded: bool = True,
                    max_steps: int | None = None) -> Recording:
    """Run ``episodes`` deterministic deployment episodes (the deployment loop,
    ``common.evaluation.deployment``) and record every decision."""
    rec = Recorder()
    evaluate_policy(params, env_cfg, episodes, seed=seed, shielded=shielded, max_steps=max_steps, recorder=rec)
    return rec.recording(params, env_cfg, seed, shielded)


def payload_pose(env) -> np.ndarray:
    """Payload (x, y, yaw) per env at the observation just returned, [K, 3] (BatchEnv's snapshot)."""
    snap = env.snap
    return np.concatenate([np.asarray(snap.pxy, np.float64), np.asarray(snap.pyaw, np.float64)[:, None]], axis=1)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return x
