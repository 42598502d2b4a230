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


@pytest.mark.parametrize("state_dim", [0, 4])
def test_written_out_value_gradient_matches_autograd(state_dim):
    """The learner's critic path (``values``, ``value_loss_and_grads``) against
    ``forward`` under autograd on the same batch: float64 to rounding, and float32 at
    the paper's widths to float32 rounding (numpy's tanh differs from torch's by an ulp)."""
    torch.manual_seed(1)
    for dtype, hidden, latent, tol in ((torch.float64, 16, 8, 1e-12), (torch.float32, 128, 32, 1e-5)):
        critic = TeamCritic(n_agents=3, obs_dim=5, state_dim=state_dim, hidden=hidden, latent=latent).to(dtype)
        obs = torch.randn(64, 3, 5, dtype=dtype)
        s = torch.randn(64, state_dim, dtype=dtype) if state_dim else None
        target = torch.randn(64, dtype=dtype)
        v = critic(obs, s)
        loss = 0.7 * (v - target).pow(2).mean()
        ref = torch.autograd.grad(loss, list(critic.parameters()))
        fast_loss, grads = critic.value_loss_and_grads(obs, s, target, 0.7)
        torch.testing.assert_close(critic.values(obs, s), v.detach(), rtol=tol, atol=tol)
        torch.testing.assert_close(fast_loss, loss.detach(), rtol=tol, atol=tol)
        assert len(grads) == len(ref)
        for (name, p), g, r in zip(critic.named_parameters(), grads, ref):
            assert g.shape == p.shape, name
            scale = float(r.abs().max())
            torch.testing.assert_close(g / scale, r / scale, rtol=tol, atol=tol, msg=name)
    with pytest.raises(ValueError):
        critic.values(obs[:, :2], s)
    if state_dim:
        with pytest.raises(ValueError):
            critic.value_loss_and_grads(obs, None, target, 1.0)


def test_learner_critic_step_is_the_autograd_step():
    """``Method._critic_step`` (written-out gradient) moves the critic as the autograd
    reference step does: same loss, clipping and Adam, from the same start."""
    from common.algos.methods import make_method
    from common.algos.adam import Adam
    cfg = AlgoConfig(critic_hidden=16, encoder_latent=4, max_grad_norm=0.05)   # the clip binds
    m = make_method("happo", cfg, 5, 15)
    ref = TeamCritic(3, 5, 0, hidden=16, latent=4)
    ref.load_state_dict(m.critic.state_dict())
    opt = Adam(ref.parameters(), lr=cfg.critic_lr, eps=1e-5)

    class MB:
        obs, state, ret = torch.randn(32, 3, 5), torch.zeros(32, 0), torch.randn(32)
    for _ in range(3):
        stats = m._critic_step(MB)
        loss = cfg.vf_coef * (ref(MB.obs) - MB.ret).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(ref.parameters(), cfg.max_grad_norm)
        opt.step()
        assert stats["value_loss"] == pytest.approx(float(loss.detach()), rel=1e-5)
    for (name, p), q in zip(m.critic.named_parameters(), ref.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6, msg=name)


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
