"""Centralized critic with a team-averaged context (Eq. team_context), value
normalization and generalized advantage estimation on executed transitions."""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from common.algos.adam import clip_grad_norm


class TeamCritic(nn.Module):
    """``V_omega(o, z)`` with ``z = mean_i psi_phi(o_i)`` (Eq. team_context).

    ``psi_phi`` is one encoder shared by all carriers, so ``z`` is invariant to
    the carrier order. ``V`` sees the concatenated observations and ``z``; with
    ``state_dim > 0`` it also sees the environment's global state (the
    ``critic_uses_state`` option; off by default to match the paper). Outputs
    are in normalized value units (see ``ValueNormalizer``).
    """

    def __init__(self, n_agents: int, obs_dim: int, state_dim: int = 0,
                 hidden: int = 128, latent: int = 32):
        super().__init__()
        self.n_agents, self.obs_dim, self.state_dim = n_agents, obs_dim, state_dim
        self.encoder = nn.Sequential(
            nn.Linear(obs_dim, hidden), nn.Tanh(), nn.Linear(hidden, latent), nn.Tanh()
        )
        self.value = nn.Sequential(
            nn.Linear(n_agents * obs_dim + latent + state_dim, hidden), nn.Tanh(),
            nn.Linear(hidden, hidden), nn.Tanh(),
            nn.Linear(hidden, 1),
        )

    def forward(self, obs: Tensor, state: Tensor | None = None) -> Tensor:
        """obs ``[B, N, obs_dim]``, state ``[B, S]`` -> value ``[B]``."""
        if obs.dim() != 3 or obs.shape[1:] != (self.n_agents, self.obs_dim):
            raise ValueError(f"critic expects obs [B,{self.n_agents},{self.obs_dim}], got {tuple(obs.shape)}")
        z = self.encoder(obs).mean(dim=1)                      # Eq. (team_context)
        parts = [obs.flatten(1), z]
        if self.state_dim:
            if state is None or state.shape[-1] != self.state_dim:
                raise ValueError(f"critic expects state [B,{self.state_dim}]")
            parts.append(state)
        return self.value(torch.cat(parts, dim=-1)).squeeze(-1)

    # The learner's path: the same network written out layer by layer, its backward by
    # hand. ``forward`` (autograd) stays the reference: tests/test_algos_critic.py checks
    # values and gradients against it. Two things pay (docs/scaling.md, "the critic
    # written out"): tanh through numpy (torch's float32 tanh costs ~7x numpy's on this CPU; the
    # two differ by at most one ulp) and no graph bookkeeping; the backward also skips
    # the gradient of the observations' slice of the value net's input.

    def _layers(self) -> list[tuple[Tensor, Tensor]]:
        e0, e2 = self.encoder[0], self.encoder[2]
        v0, v2, v4 = self.value[0], self.value[2], self.value[4]
        return [(m.weight.detach(), m.bias.detach()) for m in (e0, e2, v0, v2, v4)]

    def _forward_parts(self, obs: Tensor, state: Tensor | None, layers) -> list[Tensor]:
        """[x0, a1, a2, inp, h1, h2, v]: the encoder's input and activations over all
        B*N carrier rows, the value net's input ``[o, z, s]``, activations and ``v [B]``."""
        if obs.dim() != 3 or obs.shape[1:] != (self.n_agents, self.obs_dim):
            raise ValueError(f"critic expects obs [B,{self.n_agents},{self.obs_dim}], got {tuple(obs.shape)}")
        (w1, b1), (w2, b2), (u1, c1), (u2, c2), (u3, c3) = layers
        B = obs.shape[0]
        x0 = obs.detach().reshape(B * self.n_agents, self.obs_dim)
        a1 = _tanh_(torch.addmm(b1, x0, w1.t()))
        a2 = _tanh_(torch.addmm(b2, a1, w2.t()))
        z = a2.view(B, self.n_agents, -1).mean(dim=1)           # Eq. (team_context)
        parts = [obs.detach().reshape(B, -1), z]
        if self.state_dim:
            if state is None or state.shape[-1] != self.state_dim:
                raise ValueError(f"critic expects state [B,{self.state_dim}]")
            parts.append(state.detach())
        inp = torch.cat(parts, dim=-1)
        h1 = _tanh_(torch.addmm(c1, inp, u1.t()))
        h2 = _tanh_(torch.addmm(c2, h1, u2.t()))
        v = torch.addmm(c3, h2, u3.t()).squeeze(-1)
        return [x0, a1, a2, inp, h1, h2, v]

    @torch.no_grad()
    def values(self, obs: Tensor, state: Tensor | None = None) -> Tensor:
        """``forward``'s values without a graph (batch preparation)."""
        return self._forward_parts(obs, state, self._layers())[-1]

    @torch.no_grad()
    def value_loss_and_grads(self, obs: Tensor, state: Tensor | None, target: Tensor,
                             coef: float) -> tuple[Tensor, list[Tensor]]:
        """``coef * mean((V - target)^2)`` and its gradient for each of ``parameters()``
        (in that order), by the chain rule through the layers above."""
        layers = self._layers()
        x0, a1, a2, inp, h1, h2, v = self._forward_parts(obs, state, layers)
        (_, _), (w2, _), (u1, _), (u2, _), (u3, _) = layers
        B, N = v.shape[0], self.n_agents
        r = v - target
        loss = coef * r.pow(2).mean()
        g_v = (coef / B) * (2.0 * r)                             # d loss / d v, [B]
        g_u3, g_c3 = g_v.unsqueeze(0).mm(h2), g_v.sum().reshape(1)
        g = torch.ops.aten.tanh_backward(g_v.unsqueeze(1).mm(u3), h2)
        g_u2, g_c2 = g.t().mm(h1), g.sum(0)
        g = torch.ops.aten.tanh_backward(g.mm(u2), h1)
        g_u1, g_c1 = g.t().mm(inp), g.sum(0)
        z0 = N * self.obs_dim                                    # z's columns of the input
        g_z = g.mm(u1[:, z0:z0 + w2.shape[0]])                   # [B, latent]
        g_a2 = (g_z / N).unsqueeze(1).expand(B, N, -1).reshape(B * N, -1)   # the mean's backward
        g = torch.ops.aten.tanh_backward(g_a2, a2)
        g_w2, g_b2 = g.t().mm(a1), g.sum(0)
        g = torch.ops.aten.tanh_backward(g.mm(w2), a1)
        g_w1, g_b1 = g.t().mm(x0), g.sum(0)
        return loss, [g_w1, g_b1, g_w2, g_b2, g_u1, g_c1, g_u2, g_c2, g_u3, g_c3]


def value_step(critic: TeamCritic, opt, obs: Tensor, state: Tensor | None, target: Tensor, coef: float,
               max_grad_norm: float, by_autograd: bool = False) -> float:
    """One critic step of ``opt`` on ``coef * mean((V - target)^2)``, the gradient clipped
    to ``max_grad_norm``; returns the loss. The learner's gradient is the written-out one;
    ``by_autograd``: ``forward``'s under autograd, the reference (``sage bench learner``
    times the two)."""
    if by_autograd:
        loss = coef * (critic(obs, state) - target).pow(2).mean()
        opt.zero_grad()
        loss.backward()
    else:
        loss, grads = critic.value_loss_and_grads(obs, state, target, coef)
        for p, g in zip(critic.parameters(), grads):
            p.grad = g
    clip_grad_norm(critic.parameters(), max_grad_norm)
    opt.step()
    return float(loss.detach())


def _tanh_(x: Tensor) -> Tensor:
    """tanh in place, by numpy's on a CPU tensor (see the note above)."""
    if x.device.type != "cpu":
        return x.tanh_()
    a = x.numpy()
    np.tanh(a, out=a)
    return x


class ValueNormalizer(nn.Module):
    """Running mean/std of returns (exact pooled moments, MAPPO-ValueNorm-like
    without PopArt's output rescaling). The critic regresses normalized
    returns; GAE uses denormalized values."""

    def __init__(self, eps: float = 1e-5):
        super().__init__()
        self.eps = eps
        self.register_buffer("mean", torch.zeros((), dtype=torch.float64))
        self.register_buffer("var", torch.ones((), dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: Tensor) -> None:
        x = x.detach().to(torch.float64).reshape(-1)
        n = float(x.numel())
        if n == 0:
            return
        b_mean, b_var = x.mean(), x.var(unbiased=False)
        tot = self.count + n
        delta = b_mean - self.mean
        new_mean = self.mean + delta * n / tot
        m2 = self.var * self.count + b_var * n + delta.pow(2) * self.count * n / tot
        self.mean.copy_(new_mean)
        self.var.copy_(m2 / tot)
        self.count.copy_(tot)

    @property
    def std(self) -> Tensor:
        return (self.var + self.eps).sqrt()

    def normalize(self, x: Tensor) -> Tensor:
        return ((x - self.mean) / self.std).to(x.dtype)

    def denormalize(self, x: Tensor) -> Tensor:
        return (x * self.std + self.mean).to(x.dtype)


def compute_gae(
    reward: np.ndarray, value: np.ndarray, next_value: np.ndarray,
    terminated: np.ndarray, truncated: np.ndarray, gamma: float, lam: float,
) -> tuple[np.ndarray, np.ndarray]:
    """GAE over ``[T, K]`` arrays of executed transitions.

    ``next_value[t]`` is the value of the state reached after step ``t``: the
    next row's state, or the pre-reset ``final_obs/final_state`` where the
    episode was truncated (time limit: bootstrap), or the rollout's last state
    at ``t = T-1``. Termination zeroes the bootstrap; either end cuts the
    lambda-trace. Returns ``(advantages, returns)`` with ``returns = adv + value``.
    """
    reward = np.asarray(reward, dtype=np.float64)
    shape = reward.shape
    if reward.ndim != 2:
        raise ValueError(f"GAE expects [T, K] arrays, got reward {shape}")
    for name, arr in (("value", value), ("next_value", next_value),
                      ("terminated", terminated), ("truncated", truncated)):
        if np.shape(arr) != shape:
            raise ValueError(f"GAE: {name} has shape {np.shape(arr)}, expected {shape}")
    term = np.asarray(terminated, dtype=bool)
    done = term | np.asarray(truncated, dtype=bool)
    value = np.asarray(value, dtype=np.float64)
    next_value = np.asarray(next_value, dtype=np.float64)
    delta = reward + gamma * np.where(term, 0.0, next_value) - value
    adv = np.zeros(shape, dtype=np.float64)
    running = np.zeros(shape[1], dtype=np.float64)
    for t in range(shape[0] - 1, -1, -1):
        running = delta[t] + gamma * lam * np.where(done[t], 0.0, running)
        adv[t] = running
    return adv, adv + value


def next_values(value: np.ndarray, last_value: np.ndarray, final_value: np.ndarray,
                truncated: np.ndarray) -> np.ndarray:
    """Assemble ``next_value`` for ``compute_gae`` from ``value [T,K]``, the
    value after the last step ``[K]`` and the pre-reset values ``[T,K]`` (used
    where ``truncated``)."""
    nxt = np.concatenate([value[1:], np.asarray(last_value)[None]], axis=0)
    return np.where(np.asarray(truncated, dtype=bool), final_value, nxt)
