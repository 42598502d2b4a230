"""Synthetic contextual-bandit batches for learner tests and `sage bench learner`.

Each step is a one-step episode (``terminated`` everywhere): observations are
random, safety rows are random affine rows that are feasible at a reference
action, and the reward is ``-||a_exec - target(o)||^2`` with a fixed smooth
per-carrier target. The batch is collected exactly as an actor would
(common.policy.rollout.propose on the exported parameters): hard tree forward,
proposal center (SAIL or identity at the method's kappa), proposal sample and
its log-density.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.policy.rollout import propose
from common.safety_rows import SafetyRows
from common.spec import CARRIER_ACT_DIM, N_CARRIERS

D = N_CARRIERS * CARRIER_ACT_DIM


@dataclass
class BanditTask:
    """``reward = -||a - target(o)||^2``, ``target_i(o) = 0.8 tanh(G_i o_i)``;
    a human-occupied block (``human_rate``) plays the target action."""
    obs_dim: int
    seed: int = 0
    n_rows: int = 34
    row_frac: float = 0.3      # share of row slots in use
    human_rate: float = 0.0    # probability that a step has a human-occupied block

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        self.G = rng.normal(size=(N_CARRIERS, CARRIER_ACT_DIM, self.obs_dim)) / np.sqrt(self.obs_dim)

    def target(self, obs: np.ndarray) -> np.ndarray:
        """obs [..., N, O] -> target [..., D]."""
        t = 0.8 * np.tanh(np.einsum("iao,...io->...ia", self.G, obs))
        return t.reshape(*obs.shape[:-2], D)

    def reward(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        return -np.sum((action - self.target(obs)) ** 2, axis=-1)

    def sample_context(self, rng: np.random.Generator, T: int, K: int) -> dict[str, np.ndarray]:
        obs = rng.normal(size=(T, K, N_CARRIERS, self.obs_dim)).astype(np.float32)
        C = rng.normal(size=(T, K, self.n_rows, D))
        # rows satisfied by the target action with margins in [0, 1), so the
        # best safe policy is the target itself
        a_ref = self.target(obs.astype(np.float64))
        c = np.einsum("tkmd,tkd->tkm", C, a_ref) - rng.uniform(0.0, 1.0, size=(T, K, self.n_rows))
        row_mask = rng.random((T, K, self.n_rows)) < self.row_frac
        fixed = np.zeros((T, K, D), dtype=bool)
        if self.human_rate > 0:
            human = rng.random((T, K)) < self.human_rate
            slot = rng.integers(0, N_CARRIERS, size=(T, K))
            for i in range(N_CARRIERS):
                fixed[..., CARRIER_ACT_DIM * i:CARRIER_ACT_DIM * (i + 1)] |= (human & (slot == i))[..., None]
        return {"obs": obs, "C": C, "c": c, "row_mask": row_mask, "fixed_mask": fixed,
                "state": obs.reshape(T, K, -1).copy()}


def collect(method, task: BanditTask, T: int, K: int, progress: float,
            rng: np.random.Generator) -> dict[str, np.ndarray]:
    """One batch in the learner's layout (docs/interfaces.md, common/algos),
    proposed by the actors' own step logic (common.policy.rollout.propose)."""
    ctx = task.sample_context(rng, T, K)
    settings = method.actor_settings(progress)
    B = T * K
    obs = ctx["obs"].reshape(B, N_CARRIERS, task.obs_dim)
    rows = SafetyRows(*(ctx[k].reshape(B, *ctx[k].shape[2:]) for k in SafetyRows.FIELDS))
    out = propose(method.policy_params(), obs, rows, task.target(obs), rng, "train",
                  kappa=settings["kappa"], use_sail=method.uses_sail)
    a_exec = out["a_prop"]                      # no shield: the bandit has no dynamics
    reward = task.reward(obs, a_exec)
    shape = (T, K)
    return {
        **ctx,
        **{k: out[k].reshape(*shape, D) for k in ("a_st", "a_bar", "a_prop")},
        "a_exec": a_exec.reshape(*shape, D),
        "logp": out["logp"].reshape(*shape, N_CARRIERS),
        "leaf": out["leaf"].reshape(*shape, N_CARRIERS),
        "reward": reward.reshape(shape).astype(np.float32),
        "terminated": np.ones(shape, dtype=bool),
        "truncated": np.zeros(shape, dtype=bool),
        "final_obs": np.zeros_like(ctx["obs"]),
        "final_state": np.zeros_like(ctx["state"]),
        "last_obs": ctx["obs"][-1].copy(),
        "last_state": ctx["state"][-1].copy(),
    }
