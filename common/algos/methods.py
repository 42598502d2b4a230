"""The learner of Sec. III / IV on hard-tree actors: one ``Method`` per method of
Table I (plus the ``joint_cbf`` ablation), CleanRL-style: state here, each role in
its own module.

| role                                                   | module                          |
|--------------------------------------------------------|---------------------------------|
| what a method is (shield, SAIL, TALO, update step)     | common/algos/registry.py        |
| batch checks, GAE/returns, ``Minibatch``               | common/algos/batch.py           |
| a_ST, SAIL center, log-ratios, PPO surrogates          | common/algos/proposal_map.py    |
| the surrogates' derivatives from a_ST in closed form   | common/algos/surrogate_chain.py |
| sequential (HAPPO) update step                         | common/algos/sequential.py      |
| joint (TALO / g_ind) update step                       | common/algos/joint.py           |
| g_TALO, W_gap and its HVP                              | common/algos/talo.py            |
| W_gap/cos trace, frozen-minibatch A/B, QP correction   | common/algos/diagnostics.py     |
| centralized critic, value normalizer, GAE              | common/algos/critic.py          |

The shield itself runs on the actor side; for the learner ``shielded`` only
records that rewards come from ``a_exec``. The likelihood is always the
proposal density at the stored ``a_prop`` (Eq. action_chain).

One update: prepare the batch (critic values, GAE), snapshot the start policy (the
diagnostics' reference), then for each epoch and minibatch the registry's update
step (which also measures W_gap and cos(g_ind, g_team) before it steps), the local
claim's A/B on the update's last minibatch (``Method.local_ab``, every
``mech_ab_every``-th update), and the critic step (its own Adam, after the actors).
See docs/interfaces.md for the full list of ``update`` diagnostics.
"""
from __future__ import annotations

import contextlib
import json

import numpy as np
import torch
from torch import Tensor

from common.algos import diagnostics
from common.algos.adam import Adam
from common.algos.batch import Minibatch, prepare_batch
from common.algos.config import AlgoConfig, kappa_schedule, tau_schedule
from common.algos.critic import TeamCritic, ValueNormalizer, value_step
from common.algos.diagnostics import gap_summary, logratio_at_start, qp_diagnostics, snapshot
from common.algos.joint import joint_step
from common.algos.proposal_map import ProposalMap
from common.algos.registry import UPDATE_STEPS, method_spec
from common.algos.sequential import sequential_step
from common.policy.tree import TreeConfig
from common.policy.tree_torch import TeamPolicy
from common.spec import N_CARRIERS

STATE_FORMAT_VERSION = 1


def subnormals_flushed() -> bool:
    """Does this thread flush subnormal floats to zero (the x86 FTZ/DAZ flags)?"""
    return float(torch.tensor([5e-324], dtype=torch.float64).mul(1.0)) == 0.0


@contextlib.contextmanager
def flush_subnormals():
    """Subnormals to zero in this thread for the block, the flag restored after. The
    update's cotangents reach 1e-308 (saturated sigmoids and tanh, clipped ratios), and each
    elementwise op on a tensor holding some runs about 9x slower
    (docs/scaling.md, "The learner"); values that small are zero to every result here."""
    before = subnormals_flushed()
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(before)

# the registry's ``MethodSpec.step`` -> the function that steps the actors on one minibatch:
# step(method, minibatch, tau, kappa) -> (stats, W_gap/cos before the step: a ``GapAtStart``)
STEP_FUNCTIONS = {"sequential": sequential_step, "joint": joint_step}
assert tuple(STEP_FUNCTIONS) == UPDATE_STEPS


class Method:
    """One learner: hard-tree team policy, centralized critic, optimizers and schedules."""

    def __init__(self, name: str, cfg: AlgoConfig, obs_dim: int, state_dim: int,
                 n_agents: int = N_CARRIERS):
        spec = method_spec(name)
        if obs_dim < 1 or state_dim < 0:
            raise ValueError(f"bad dims obs_dim={obs_dim}, state_dim={state_dim}")
        self.name, self.cfg = name, cfg
        self.obs_dim, self.state_dim, self.n_agents = int(obs_dim), int(state_dim), n_agents
        self.shielded, self.uses_sail, self.uses_talo = spec.shielded, spec.uses_sail, spec.uses_talo
        self.joint_step = spec.joint_step
        self.update_step = STEP_FUNCTIONS[spec.step]
        with torch.random.fork_rng():
            torch.manual_seed(cfg.seed)
            self.policy = TeamPolicy(
                n_agents, obs_dim,
                config=TreeConfig(depth=cfg.tree_depth, init_log_std=cfg.init_log_std,
                                  split_k=cfg.split_k, leaf_k=cfg.leaf_k),
            )
            self.critic = TeamCritic(
                n_agents, obs_dim, state_dim if cfg.critic_uses_state else 0,
                hidden=cfg.critic_hidden, latent=cfg.encoder_latent,
            )
        self.value_norm = ValueNormalizer()
        self.proposal = ProposalMap(self.policy, self.uses_sail, cfg.sail_grad, cfg.clip)
        self.trees, self.groups, self.actor_params = self.proposal.trees, self.proposal.groups, self.proposal.params
        # one Adam per carrier (HARL style; the joint step steps all of them together)
        self.actor_opts = [Adam(g, lr=cfg.actor_lr, eps=1e-5) for g in self.groups]
        self.critic_opt = Adam(self.critic.parameters(), lr=cfg.critic_lr, eps=1e-5)
        self.gen = torch.Generator().manual_seed(cfg.seed + 1)
        self.updates = 0
        self.last_happo_factors: dict[int, Tensor] = {}   # carrier -> M used (for tests)
        self.last_happo_orders: list[list[int]] = []      # carrier order of each minibatch of the last update

    # ------------------------------------------------------------------ public API

    def actor_settings(self, progress: float) -> dict[str, float]:
        """Schedules shared with the actors. ``kappa = 0`` means the identity
        center (Pi_0 is the identity), used by the methods without SAIL."""
        return {
            "kappa": kappa_schedule(self.cfg, progress) if self.uses_sail else 0.0,
            "tau": tau_schedule(self.cfg, progress),
        }

    def policy_params(self) -> dict[str, np.ndarray]:
        return self.policy.export_params()

    def update(self, batch: dict[str, np.ndarray], progress: float) -> dict[str, float]:
        """One learner update on a rollout batch (see docs/interfaces.md)."""
        with flush_subnormals():
            return self._update(batch, progress)

    def _update(self, batch: dict[str, np.ndarray], progress: float) -> dict[str, float]:
        settings = self.actor_settings(progress)
        tau, kappa = settings["tau"], settings["kappa"]
        data, batch_diag = self._prepare(batch)
        data = self.proposal.prepared(data)
        batch_diag.update(qp_diagnostics(batch, self.cfg.diag_qp_samples))
        B = data.obs.shape[0]
        n_mb = min(self.cfg.minibatches, B)
        sums: dict[str, float] = {}
        counts: dict[str, int] = {}

        def log(stats: dict[str, float]) -> None:
            for k, v in stats.items():
                sums[k] = sums.get(k, 0.0) + float(v)
                counts[k] = counts.get(k, 0) + 1

        # the diagnostics' reference: the policy at the update's start, on every sample
        data.logp_start = self.proposal.start_log_prob(data, tau, kappa)
        batch_diag["logratio_at_start"] = logratio_at_start(data)
        self.last_happo_orders = []
        w_trace, cos_trace = [], []
        ab = self.cfg.mech_ab_every > 0 and self.updates % self.cfg.mech_ab_every == 0
        for epoch in range(self.cfg.epochs):
            perm = torch.randperm(B, generator=self.gen)
            for j, idx in enumerate(torch.tensor_split(perm, n_mb)):
                mb = data.index(idx)
                if epoch == 0 and j == 0:
                    # at the start parameters: the forward is its own reference (ratio exactly 1,
                    # not 1 +- the rounding of a differently shaped batch's forward)
                    mb.logp_start = None
                before = snapshot(self.actor_params)
                stats, gap = self.update_step(self, mb, tau, kappa)
                step_norm = float(torch.cat([(p.detach() - b).double().reshape(-1)
                                             for p, b in zip(self.actor_params, before)]).norm())
                stats["actor_step_norm"] = step_norm
                # W_gap, cos(g_ind, g_team): measured at the parameters before this minibatch's step
                w_trace.append(gap.w_gap)
                cos_trace.append(gap.cos_ind_team)
                if ab and epoch == self.cfg.epochs - 1 and j == n_mb - 1:
                    length = self.cfg.mech_ab_step or step_norm
                    log(self.local_ab(mb, tau, kappa, length, at=before, gap=gap))
                log(stats)
                log(self._critic_step(mb))
        self.updates += 1
        diag = {k: sums[k] / counts[k] for k in sums}
        diag.update(gap_summary(w_trace, cos_trace))
        diag.update(batch_diag)
        diag.update(tau=tau, kappa=kappa, updates=float(self.updates))
        return diag

    def local_ab(self, mb: Minibatch, tau: float, kappa: float, length: float,
                 at: list[Tensor] | None = None, gap: diagnostics.GapAtStart | None = None) -> dict[str, float]:
        """The local claim of Eq. (talo_condition) on the frozen minibatch ``mb``: W_gap
        after a step of length ``length`` along g_TALO and along g_ind, from parameters
        ``at`` (default: the current ones; ``gap``: the step's gap there, to reuse); see
        ``diagnostics.local_ab``."""
        return diagnostics.local_ab(self.proposal, self.cfg, mb, tau, kappa, length, at=at, gap=gap)

    # ------------------------------------------------------------------ batch and critic

    def _prepare(self, batch: dict[str, np.ndarray]) -> tuple[Minibatch, dict[str, float]]:
        """The batch as one flat ``Minibatch`` and its diagnostics (moves the value normalizer)."""
        return prepare_batch(batch, self.critic, self.value_norm, self.cfg, self.n_agents, self.obs_dim)

    def _critic_step(self, mb: Minibatch) -> dict[str, float]:
        loss = value_step(self.critic, self.critic_opt, mb.obs, mb.state if self.critic.state_dim else None,
                          mb.ret, self.cfg.vf_coef, self.cfg.max_grad_norm)
        return {"value_loss": loss}

    # ------------------------------------------------------------------ checkpoints

    def state_dict(self) -> dict:
        """Weights-only-safe (tensors, numbers, strings, lists, dicts)."""
        return {
            "format_version": STATE_FORMAT_VERSION,
            "method": self.name,
            "config": json.dumps(self.cfg.to_dict(), sort_keys=True),
            "obs_dim": self.obs_dim,
            "state_dim": self.state_dim,
            "policy": self.policy.state_dict(),
            "critic": self.critic.state_dict(),
            "value_norm": self.value_norm.state_dict(),
            "actor_opts": [o.state_dict() for o in self.actor_opts],
            "critic_opt": self.critic_opt.state_dict(),
            "updates": self.updates,
            "rng": self.gen.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        if state.get("format_version") != STATE_FORMAT_VERSION:
            raise ValueError(f"unsupported learner state format {state.get('format_version')!r}")
        if state.get("method") != self.name:
            raise ValueError(f"checkpoint is for method {state.get('method')!r}, not {self.name!r}")
        if (state.get("obs_dim"), state.get("state_dim")) != (self.obs_dim, self.state_dim):
            raise ValueError("checkpoint obs_dim/state_dim do not match this learner")
        self.policy.load_state_dict(state["policy"])
        self.critic.load_state_dict(state["critic"])
        self.value_norm.load_state_dict(state["value_norm"])
        if len(state["actor_opts"]) != len(self.actor_opts):
            raise ValueError("checkpoint has a different number of actor optimizers")
        for opt, s in zip(self.actor_opts, state["actor_opts"]):
            opt.load_state_dict(s)
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.updates = int(state["updates"])
        self.gen.set_state(state["rng"])


def make_method(name: str, cfg: AlgoConfig | None, obs_dim: int, state_dim: int) -> Method:
    """Factory named in docs/interfaces.md."""
    return Method(name, cfg or AlgoConfig(), obs_dim, state_dim)
