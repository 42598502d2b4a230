"""The joint update step (registry ``step="joint"``: TALO+CBF, SAGE and the
Joint+CBF ablation): all carriers stepped together along one flat direction,
``g_TALO`` (Eqs. talo_gap .. talo_projection, common/algos/talo.py: one HVP per
minibatch on the full actor parameter vector) for the TALO methods, ``g_ind`` for
Joint+CBF.

``AlgoConfig.talo_step`` picks how the direction is applied:
"adam": per-carrier Adam after global norm clipping, the entropy gradient added
after the projection; "direct": ``theta <- theta + talo_eta g`` with the entropy
gradient inside ``g_ind`` before the projection, no clipping, so the applied step
itself meets Eq. (talo_condition).
"""
from __future__ import annotations

import torch

from common.algos.adam import clip_grad_norm
from common.algos.batch import Minibatch
from common.algos.diagnostics import GapAtStart, snapshot, talo_condition
from common.algos.talo import flat_grad, talo_project, unflatten_like


def joint_step(learner, mb: Minibatch, tau: float, kappa: float) -> tuple[dict[str, float], GapAtStart]:
    """One joint step of ``learner`` (a ``Method``: its ``proposal``, ``actor_opts``,
    ``cfg`` and ``uses_talo``) on ``mb``. Returns (stats, W_gap/cos measured before
    the step, ratios against the update's start: a ``GapAtStart``)."""
    cfg, proposal = learner.cfg, learner.proposal
    params = proposal.params
    a_st, _, behaviour, start = proposal.start_point(mb, tau, kappa)
    log_ratio, L_ind, L_team = behaviour.log_ratio, behaviour.L_ind, behaviour.L_team
    # the algorithm's gap: ratios against the behaviour policy (Eq. ppo_surrogates)
    g_ind, g_team, w, grad_w = proposal.gap(a_st, behaviour, with_hvp=learner.uses_talo)
    # the diagnostics' gap: ratios against the update's start (the same one on-policy)
    gap = GapAtStart.of(g_ind, g_team, w, a_st, start, grad_w) if start is behaviour \
        else GapAtStart.of(*proposal.gap(a_st, start, with_hvp=False)[:3], a_st, start)
    entropy = proposal.entropy()
    g_ent = cfg.ent_coef * flat_grad(entropy.sum(), params) if cfg.ent_coef > 0 \
        else torch.zeros_like(g_ind)
    direct = cfg.talo_step == "direct"
    stats = proposal.ratio_stats(log_ratio, mb.active)
    if learner.uses_talo:
        # Eq. (talo_projection). direct: entropy inside g_ind, so the step taken is the
        # projected one; adam: entropy after the projection (only touches log_std)
        g, delta = talo_project(g_ind + g_ent if direct else g_ind, grad_w, w,
                                cfg.talo_sigma, cfg.talo_eps)
        if not direct:
            g = g + g_ent
        stats.update(delta_gap=delta, talo_corrected=float(delta > 0.0))
    else:
        g = g_ind + g_ent
    before = snapshot(params) if learner.uses_talo else None
    if direct:
        with torch.no_grad():
            for p, d in zip(params, unflatten_like(g, params)):
                p.add_(d.to(p.dtype), alpha=cfg.talo_eta)
        grad_norm = float(g.norm())
    else:
        for p, d in zip(params, unflatten_like(g, params)):
            p.grad = -d.detach().clone()      # ascent on surrogates -> descent for Adam
        grad_norm = float(clip_grad_norm(params, cfg.max_grad_norm))
        for opt in learner.actor_opts:
            opt.step()
    if learner.uses_talo:
        met, decreases, floor = talo_condition(cfg, params, grad_w, w, g_ind, g_team, before, direct)
        stats.update(talo_condition_met=met, talo_step_decreases_gap=decreases,
                     talo_gap_at_floor=floor)
    stats.update(
        policy_loss=-float(sum(L_ind).detach()), team_loss=-float(L_team.detach()),
        entropy=float(entropy.detach().mean()), actor_grad_norm=grad_norm,
    )
    return stats, gap
