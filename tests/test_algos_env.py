"""Learner on a real environment batch: actors' step logic (common.policy.rollout),
the exact QP shield, MuJoCo transitions with time-limit truncation."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from common.algos import AlgoConfig, make_method


@pytest.mark.parametrize("name", ["sage", "happo_cbf"])
def test_update_on_env_batch_with_truncation(name):
    from common.env import BatchEnv, EnvConfig
    from common.policy.rollout import propose
    from common.safety_rows import SafetyRows
    from common.shield.qp import shield_actions

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        env = BatchEnv(EnvConfig(max_steps=5), 2, seed=0)
        m = make_method(name, AlgoConfig(epochs=1, minibatches=2, critic_hidden=32,
                                         encoder_latent=8, critic_uses_state=True),
                        env.obs_dim, env.state_dim)
        rng = np.random.default_rng(0)
        o = env.reset()
        cols: dict[str, list] = {}
        for _ in range(12):
            s = m.actor_settings(0.3)
            rows = SafetyRows.of(o)
            p = propose(m.policy_params(), o["obs"], rows, o["human_action"], rng, "train",
                        kappa=s["kappa"], use_sail=m.uses_sail)
            q = shield_actions(p["a_prop"], rows)
            step = {k: o[k] for k in ("obs", "state", "C", "c", "row_mask", "fixed_mask")}
            step.update({k: p[k] for k in ("a_st", "a_bar", "a_prop", "logp", "leaf")}, a_exec=q.a_exec)
            o = env.step(q.a_exec)
            step.update({k: o[k] for k in ("reward", "terminated", "truncated", "final_obs", "final_state")})
            for k, v in step.items():
                cols.setdefault(k, []).append(np.asarray(v))
        batch = {k: np.stack(v) for k, v in cols.items()}
        batch.update(last_obs=o["obs"], last_state=o["state"])
        assert batch["truncated"].any()          # the bootstrap path is exercised
        before = [p.detach().clone() for p in m.actor_params]
        diag = m.update(batch, 0.3)
    finally:
        torch.set_num_threads(threads)
    assert diag["logratio_at_start"] < 1e-5     # learner reproduces the actors' log-probs
    assert all(np.isfinite(v) for v in diag.values())
    assert any(not torch.equal(a, b) for a, b in zip(before, m.actor_params))
