"""The sequential update step (registry ``step="sequential"``: HAPPO, HAPPO+CBF and
SAIL+CBF), HAPPO's scheme (Kuba et al.; HARL's).

A random carrier order, drawn once per update (as HARL draws it once per training
call; ``AlgoConfig.happo_order = "minibatch"`` redraws it every minibatch); on each
minibatch carrier ``i_m`` maximizes ``E[min(r A M, clip(r) A M)]`` (Eq. ppo_surrogates
with the factor M), where ``M`` is the (detached) product of the updated ratios of the
carriers before it; then ``M`` is multiplied by its own new ratio. (HARL runs all
epochs of one agent before the next; here the sequence runs within every minibatch.)
SAIL+CBF uses this scheme too (the paper builds SAIL+CBF on the HAPPO baseline); a
carrier's center is computed with its partners' tree outputs detached.

The step reuses the W_gap diagnostics' forward at the minibatch's start (and its SAIL
solve): the first carrier in the order, at M = 1, steps along that forward's L_i.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from common.algos.adam import clip_grad_norm
from common.algos.batch import Minibatch
from common.algos.diagnostics import GapAtStart, gap_diagnostics
from common.algos.proposal_map import StartPoint
from common.algos.talo import flat_grad, unflatten_like
from common.policy.proposal import proposal_entropy
from common.spec import CARRIER_ACT_DIM


def sequential_step(learner, mb: Minibatch, tau: float, kappa: float) -> tuple[dict[str, float], GapAtStart]:
    """One HAPPO step of ``learner`` (a ``Method``) on ``mb``, carriers in this update's
    order (appended to ``learner.last_happo_orders``, which ``Method.update`` empties).
    Returns (stats, W_gap/cos measured before the step, ratios against the update's start:
    a ``GapAtStart``)."""
    orders = learner.last_happo_orders
    if not orders or learner.cfg.happo_order == "minibatch":
        # drawn after epoch 0's permutation, so that every method sees the same minibatches
        order = torch.randperm(learner.n_agents, generator=learner.gen).tolist()
    else:
        order = orders[-1]
    gap, start = gap_diagnostics(learner.proposal, mb, tau, kappa)
    stats = happo_step(learner, mb, tau, kappa, order=order, start=start)
    orders.append(list(order))
    return stats, gap


def happo_step(learner, mb: Minibatch, tau: float, kappa: float, order: list[int] | None = None,
               start: StartPoint | None = None) -> dict[str, float]:
    """HAPPO sequential per-carrier clipped updates with the M factor, carriers
    in ``order`` (a fresh random one if None). ``start`` = the diagnostics'
    ``StartPoint`` at the current parameters, if already computed. Records the M each
    carrier was updated with in ``learner.last_happo_factors``."""
    cfg, proposal = learner.cfg, learner.proposal
    trees, groups = proposal.trees, proposal.groups
    if order is None:
        order = torch.randperm(learner.n_agents, generator=learner.gen).tolist()
    factor = torch.ones_like(mb.adv)
    if start is not None:
        a_st_cache, step_cache = start.a_st, start.step
    else:
        with torch.no_grad():      # forward at the current parameters
            a_st_cache = proposal.tree_actions(mb, tau, grad=False)
            step_cache = proposal.sail_step(mb, a_st_cache, kappa)
    learner.last_happo_factors = {}
    losses, kls, clips, ents, norms = [], [], [], [], []
    for i in order:
        learner.last_happo_factors[i] = factor.clone()
        tree = trees[i]
        block = slice(CARRIER_ACT_DIM * i, CARRIER_ACT_DIM * (i + 1))
        log_std = torch.cat([t.log_std if j == i else t.log_std.detach()
                             for j, t in enumerate(trees)])
        active = mb.active[:, i]
        learner.actor_opts[i].zero_grad()
        if start is not None and i == order[0]:
            # M = 1: this carrier's surrogate is L_i at the start point, on the
            # diagnostics' forward; only the entropy is added
            log_ratio, surr = start.behaviour.log_ratio[:, i].detach(), start.behaviour.L_ind[i]
            g_i = start.g_ind.split([sum(p.numel() for p in g) for g in groups])[i] \
                if start.g_ind is not None else flat_grad(surr, groups[i])
            grads = unflatten_like(g_i, groups[i])
            for p, g in zip(groups[i], grads):
                p.grad = -g                  # ascent on L_i -> descent for Adam
            surr = surr.detach()
        elif start is not None and start.behaviour.taped is not None:
            # tree i still has the start point's parameters: its tape serves, and L_i's
            # gradient (advantage scaled by M) is the closed form at the refreshed chain
            log_ratio, surr, g_i = proposal.carrier_gradient(dataclasses.replace(mb, adv=mb.adv * factor),
                                                             a_st_cache, kappa, step_cache, i,
                                                             start.behaviour.taped.forest)
            for p, g in zip(groups[i], unflatten_like(g_i, groups[i])):
                p.grad = -g
        else:
            own = tree(mb.obs[:, i], tau).action
            a_st = torch.cat([a_st_cache[:, :block.start], own, a_st_cache[:, block.stop:]], dim=-1)
            # same values as the cached forward: reuse its SAIL step, build the graph only;
            # L_i with the advantage scaled by M (Eq. ppo_surrogates with the factor)
            log_ratio, surr = proposal.carrier_surrogate(dataclasses.replace(mb, adv=mb.adv * factor),
                                                         a_st, log_std, kappa, step_cache, i)
        entropy = proposal_entropy(log_std)[i]
        loss = -(surr + cfg.ent_coef * entropy)
        loss.backward()                      # adds to a reused gradient
        norms.append(float(clip_grad_norm(groups[i], cfg.max_grad_norm)))
        learner.actor_opts[i].step()
        stats = proposal.ratio_stats(log_ratio[:, None], active[:, None])
        losses.append(float(loss.detach())); ents.append(float(entropy.detach()))
        kls.append(stats["approx_kl"]); clips.append(stats["clip_frac"])
        if i == order[-1]:
            break   # no carrier after this one: its M would go unused (saves a SAIL solve)
        # M <- M * rho_i(theta_i new)  (HARL: ratio of the updated carrier, detached)
        with torch.no_grad():
            a_st_cache[:, block] = tree(mb.obs[:, i], tau).action
            step_cache = proposal.sail_step(mb, a_st_cache, kappa)
            new = proposal.log_ratio(mb, proposal.center(mb, a_st_cache, kappa, step=step_cache),
                                     proposal.log_std())[:, i]
            factor = factor * torch.where(active, new.exp(), torch.ones_like(new))
    return {"policy_loss": float(np.sum(losses)), "approx_kl": float(np.mean(kls)),
            "clip_frac": float(np.mean(clips)), "entropy": float(np.mean(ents)),
            "actor_grad_norm": float(np.mean(norms)),
            # spread of the M factor the last carrier in the order was updated with
            "happo_factor_std": float(factor.std()) if factor.numel() > 1 else 0.0}
