"""Method-blind calibration of the scenario distributions with the scripted controller only
(issue 29): per scenario, four arms on held-out layouts (the eval layout stream):

* ``clean``: the scripted reference controller, unshielded;
* ``clean+shield``: the same under the exact joint CBF-QP (Eq. qpshield);
* ``biased``: the controller aimed ``aim_offset`` (0.2 m) left of the route, its action the
  centre of the default proposal (tanh-squashed Gaussian, ``log_std`` = AlgoConfig.init_log_std;
  ``common.policy.proposal``), unshielded;
* ``biased+shield``: the same under the shield.

Each arm runs one env per episode until every env finished its first episode (as
``deployment.evaluate_policy``) and reports success, drop and truncation (time limit: a
deadlock or a too-slow run) rates separately, collisions (episodes with wall contact, pooled
contact steps per 1k), and for shielded arms the QP's intervention rate (steps whose executed
action differs from the proposal by > 1e-6) and its infeasible steps. No learned policy is
involved: the spreads are set from these figures and physical grounds only.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from common.env.batch_env import BatchEnv
from common.env.config import EnvConfig
from common.env.scripted import scripted_actions
from common.policy.proposal import proposal_sample_np
from common.safety_rows import SafetyRows
from common.shield.qp import STATUS_INFEASIBLE, shield_actions

ARMS = ("clean", "clean+shield", "biased", "biased+shield")
INTERVENTION_TOL = 1e-6


def run_arm(env_cfg: EnvConfig, episodes: int, seed: int, arm: str, aim_offset: float = 0.2,
            log_std: float = -0.5) -> dict:
    """One arm (module docstring) on ``episodes`` held-out episodes of ``env_cfg``'s scenario."""
    if arm not in ARMS:
        raise ValueError(f"arm must be one of {ARMS}, got {arm!r}")
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    biased, shielded = arm.startswith("biased"), arm.endswith("+shield")
    env = BatchEnv(env_cfg, episodes, seed=seed, layout_purpose="eval")
    noise_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0xCA1,)))
    std = np.full(env.n_agents * env.act_dim, float(log_std))
    out = env.reset()
    first: list[dict | None] = [None] * episodes
    steps = interventions = infeasible = 0
    for _ in range(env.max_steps + 1):
        live = np.array([f is None for f in first])
        if not live.any():
            break
        a = scripted_actions(env.snap, env_cfg, aim_offset=aim_offset if biased else 0.0)
        if biased:
            a, _ = proposal_sample_np(a, std, noise_rng)
        if shielded:
            res = shield_actions(a, SafetyRows.of(out))   # Eq. (qpshield)
            interventions += int(((res.correction_norm > INTERVENTION_TOL) & live).sum())
            infeasible += int(((res.status == STATUS_INFEASIBLE) & live).sum())
            a = res.a_exec
        steps += int(live.sum())
        out = env.step(a)
        for k, ep in zip(np.flatnonzero(out["terminated"] | out["truncated"]), out["episodes"]):
            if first[k] is None:
                first[k] = ep
    eps = [e for e in first if e is not None]
    n = len(eps)
    sr = sum(e["success"] for e in eps) / n
    dr = sum(e["drop"] for e in eps) / n
    return {
        "arm": arm, "episodes": n, "success_rate": sr, "drop_rate": dr, "truncation_rate": 1.0 - sr - dr,
        "collision_episode_rate": sum(e["collision_steps"] > 0 for e in eps) / n,
        "col_per_1k_pooled": 1000.0 * sum(e["collision_steps"] for e in eps) / max(sum(e["steps"] for e in eps), 1),
        "intervention_rate": interventions / max(steps, 1) if shielded else None,
        "infeasible_steps": infeasible if shielded else None,
        "min_clearance_mean": float(np.mean([e["min_clearance"] for e in eps])),
        "steps": steps,
    }


def calibrate(scenarios, episodes: int = 40, seed: int = 0, layout_spread: float | None = None,
              aim_offset: float = 0.2, log_std: float = -0.5) -> dict:
    """``{scenario: {arm: run_arm(...)}}`` for every scenario and arm (module docstring)."""
    out = {}
    for name in scenarios:
        cfg = EnvConfig(name)
        if layout_spread is not None:
            cfg = dataclasses.replace(cfg, layout_spread=layout_spread)
        out[name] = {arm: run_arm(cfg, episodes, seed, arm, aim_offset, log_std) for arm in ARMS}
    return out
