"""Critic, value normalizer and GAE (common/algos/critic.py) against references."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from common.algos.config import AlgoConfig, kappa_schedule, tau_schedule
from common.algos.critic import TeamCritic, ValueNormalizer, compute_gae, next_values


def reference_gae(reward, value, last_value, final_value, terminated, truncated, gamma, lam):
    """Per-env, per-step loop written from the definition:
    A_t = sum_l (gamma*lam)^l delta_{t+l} until the episode (or rollout) ends."""
    T, K = reward.shape
    adv = np.zeros((T, K))
    for k in range(K):
        for t in range(T):
            total, decay = 0.0, 1.0
            for u in range(t, T):
                if terminated[u, k]:
                    boot = 0.0
                elif truncated[u, k]:
                    boot = final_value[u, k]
                elif u + 1 < T:
                    boot = value[u + 1, k]
                else:
                    boot = last_value[k]
                delta = reward[u, k] + gamma * boot - value[u, k]
                total += decay * delta
                if terminated[u, k] or truncated[u, k]:
                    break
                decay *= gamma * lam
            adv[t, k] = total
    return adv


@pytest.mark.parametrize("seed", range(4))
def test_gae_matches_reference_loop_with_truncation(seed):
    rng = np.random.default_rng(seed)
    T, K = 9, 5
    reward = rng.normal(size=(T, K))
    value = rng.normal(size=(T, K))
    last_value = rng.normal(size=K)
    final_value = rng.normal(size=(T, K))
    terminated = rng.random((T, K)) < 0.15
    truncated = rng.random((T, K)) < 0.15
    truncated[T - 1, 0] = True          # truncation on the last row
    terminated[3, 1] = truncated[3, 1] = True   # both: termination wins
    gamma, lam = 0.97, 0.9
    nxt = next_values(value, last_value, final_value, truncated)
    adv, ret = compute_gae(reward, value, nxt, terminated, truncated, gamma, lam)
    ref = reference_gae(reward, value, last_value, final_value, terminated, truncated, gamma, lam)
    np.testing.assert_allclose(adv, ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(ret, ref + value, rtol=1e-12, atol=1e-12)


def test_gae_hand_values():
    # one env, 3 steps, truncated at t=1 (bootstrap from final value 10),
    # terminated at t=2 (no bootstrap), gamma=0.5, lambda=1
    reward = np.array([[1.0], [2.0], [3.0]])
    value = np.array([[0.0], [0.0], [4.0]])
    final = np.array([[0.0], [10.0], [0.0]])
    term = np.array([[False], [False], [True]])
    trunc = np.array([[False], [True], [False]])
    nxt = next_values(value, np.array([99.0]), final, trunc)
    adv, _ = compute_gae(reward, value, nxt, term, trunc, gamma=0.5, lam=1.0)
    # t=2: 3 - 4 = -1 ; t=1: 2 + 0.5*10 - 0 = 7 ; t=0: 1 + 0.5*0 - 0 + 0.5*7 = 4.5
    np.testing.assert_allclose(adv[:, 0], [4.5, 7.0, -1.0])


def test_gae_rejects_bad_shapes():
    with pytest.raises(ValueError):
        compute_gae(np.zeros((3, 2)), np.zeros((3, 2)), np.zeros((3, 1)),
                    np.zeros((3, 2), bool), np.zeros((3, 2), bool), 0.9, 0.9)


def test_value_normalizer_matches_pooled_moments():
    rng = np.random.default_rng(0)
    chunks = [rng.normal(3.0, 2.0, size=n) for n in (5, 40, 1, 17)]
    norm = ValueNormalizer(eps=0.0)
    for ch in chunks:
        norm.update(torch.tensor(ch))
    allv = np.concatenate(chunks)
    assert float(norm.mean) == pytest.approx(allv.mean(), rel=1e-12)
    assert float(norm.var) == pytest.approx(allv.var(), rel=1e-12)
    x = torch.tensor(allv)
    torch.testing.assert_close(norm.denormalize(norm.normalize(x)), x)


def test_team_context_is_carrier_order_invariant_and_state_is_used():
    torch.manual_seed(0)
    critic = TeamCritic(n_agents=3, obs_dim=5, state_dim=4, hidden=16, latent=8)
    obs = torch.randn(7, 3, 5)
    perm = obs[:, [2, 0, 1]]
    z = critic.encoder(obs).mean(1)
    torch.testing.assert_close(critic.encoder(perm).mean(1), z)
    s = torch.randn(7, 4)
    v1, v2 = critic(obs, s), critic(obs, s + 1.0)
    assert v1.shape == (7,) and not torch.allclose(v1, v2)
    with pytest.raises(ValueError):
        critic(obs[:, :2], s)
    with pytest.raises(ValueError):
        critic(obs, None)


def test_schedules_and_config_validation():
    cfg = AlgoConfig()
    assert tau_schedule(cfg, 0.0) == pytest.approx(cfg.tau_start)
    assert tau_schedule(cfg, 1.0) == pytest.approx(cfg.tau_end)
    assert tau_schedule(cfg, 0.5) == pytest.approx((cfg.tau_start * cfg.tau_end) ** 0.5)
    assert kappa_schedule(cfg, 2.0) == pytest.approx(cfg.kappa_end)   # clipped
    ks = [kappa_schedule(cfg, p) for p in np.linspace(0, 1, 11)]
    assert all(b > a for a, b in zip(ks, ks[1:]))
    with pytest.raises(ValueError):
        AlgoConfig(clip=0.0)
    with pytest.raises(ValueError):
        AlgoConfig.from_dict({"nope": 1})
    assert AlgoConfig.from_dict(cfg.to_dict()) == cfg
