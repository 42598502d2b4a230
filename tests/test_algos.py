"""The learning methods (common/algos/methods.py and its step modules, Table I plus the joint_cbf
ablation) on synthetic batches."""
from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from common.algos import AlgoConfig, make_method
from common.algos.registry import ALL_METHODS
from common.algos.sequential import happo_step
from common.algos.synthetic import BanditTask, collect
from common.algos.talo import individual_gradient, talo_gap, unflatten_like
from common.policy.sail import SailConfig, sail_center_implicit, sail_project

OBS = 6


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def small_batch(method, seed=0, T=6, K=8, human_rate=0.2, progress=0.5):
    task = BanditTask(obs_dim=OBS, seed=seed, n_rows=10, row_frac=0.5, human_rate=human_rate)
    return collect(method, task, T, K, progress, np.random.default_rng(seed))


def flat_params(method):
    return torch.cat([p.detach().reshape(-1).clone() for p in method.actor_params])


@pytest.mark.parametrize("name", ALL_METHODS)
def test_update_changes_parameters_and_reports(name):
    cfg = AlgoConfig(epochs=2, minibatches=2, critic_hidden=32, encoder_latent=8)
    m = make_method(name, cfg, OBS, 3 * OBS)
    batch = small_batch(m)
    before = flat_params(m)
    critic_before = [p.detach().clone() for p in m.critic.parameters()]
    diag = m.update(batch, progress=0.5)
    assert not torch.equal(before, flat_params(m))
    assert any(not torch.equal(a, b) for a, b in zip(critic_before, m.critic.parameters()))
    for key in ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac", "w_gap",
                "cos_ind_team", "w_gap_first", "w_gap_mean", "cos_ind_team_first", "cos_ind_team_mean",
                "tau", "kappa", "proposal_violation_rate", "correction_mean", "correction_st",
                "exec_minus_prop", "sail_residual", "actor_step_norm"):
        assert key in diag and np.isfinite(diag[key]), key
    assert diag["w_gap"] == diag["w_gap_mean"] and diag["cos_ind_team"] == diag["cos_ind_team_mean"]
    assert ("talo_condition_met" in diag) == m.uses_talo
    assert ("happo_factor_std" in diag) == (not m.joint_step)
    # on-policy batch: learner's recomputed log-probs equal the actors' ones
    assert diag["logratio_at_start"] < 1e-5
    assert (diag["kappa"] > 0) == m.uses_sail
    assert m.shielded == (name != "happo")
    assert (diag["sail_residual"] > 0) == m.uses_sail
    params = m.policy_params()
    assert params["carrier_0/W"].shape[1] == OBS


def test_bad_batches_are_rejected():
    m = make_method("happo", AlgoConfig(), OBS, 0)
    batch = small_batch(m)
    with pytest.raises(ValueError, match="missing"):
        m.update({k: v for k, v in batch.items() if k != "logp"}, 0.0)
    bad = dict(batch, obs=batch["obs"][..., :-1])
    with pytest.raises(ValueError, match="obs"):
        m.update(bad, 0.0)
    trunc = dict(batch, truncated=np.ones_like(batch["truncated"]),
                 terminated=np.zeros_like(batch["terminated"]))
    trunc.pop("final_obs")
    with pytest.raises(ValueError, match="final_obs"):
        m.update(trunc, 0.0)
    with pytest.raises(ValueError, match="unknown method"):
        make_method("ppo", AlgoConfig(), OBS, 0)
    # the actors' centers are optional (the SAIL solves' warm start) but checked where present
    sage = make_method("sage", AlgoConfig(), OBS, 0)
    good = small_batch(sage)
    for a_bar, match in ((good["a_bar"][..., :-1], "a_bar.*shape"), (np.full_like(good["a_bar"], np.nan), "a_bar.*NaN")):
        with pytest.raises(ValueError, match=match):
            sage.update(dict(good, a_bar=a_bar), 0.0)
    sage.update({k: v for k, v in good.items() if k != "a_bar"}, 0.0)


def prepared(name, seed=0, double=True, human_rate=0.2):
    m = make_method(name, AlgoConfig(), OBS, 0)
    batch = small_batch(m, seed=seed, human_rate=human_rate)
    if double:
        m.policy.double()
    mb, _ = m._prepare(batch)
    return m, mb


def team_surrogates(m, mb, tau=0.5, kappa=3.0):
    a_st = m.proposal.tree_actions(mb, tau, grad=True)
    log_ratio = m.proposal.log_ratio(mb, m.proposal.center(mb, a_st, kappa), m.proposal.log_std())
    return m.proposal.surrogates(mb, log_ratio)


def test_detached_partner_surrogates_give_same_g_ind():
    """Paper recipe (partners detached before SAIL, Sec. III-D) == partials on the shared graph."""
    m, mb = prepared("sage")
    L_shared, _ = team_surrogates(m, mb)
    g_shared = individual_gradient(L_shared, m.groups)
    L_det = []
    for i in range(m.n_agents):
        a_st = m.proposal.tree_actions(mb, 0.5, grad=True)
        blocks = a_st.split(3, dim=1)                       # partners cut from the graph
        a_st = torch.cat([b if j == i else b.detach() for j, b in enumerate(blocks)], dim=1)
        log_ratio = m.proposal.log_ratio(mb, m.proposal.center(mb, a_st, 3.0), m.proposal.log_std())
        L_det.append(m.proposal.surrogates(mb, log_ratio)[0][i])
    g_det = individual_gradient(L_det, m.groups, separable=True)
    assert g_shared.norm() > 0
    torch.testing.assert_close(g_det, g_shared, rtol=1e-9, atol=1e-12)


def test_sail_implicit_gradient_matches_unrolled_map():
    """At a converged center the implicit Jacobian (Eq. sail_jacobian) equals the
    unrolled Newton map's Jacobian."""
    rng = np.random.default_rng(3)
    B, M, d = 16, 6, 9
    a = torch.tensor(rng.uniform(-0.8, 0.8, (B, d)), requires_grad=True)
    C = torch.tensor(rng.normal(size=(B, M, d)))
    c = torch.tensor(rng.normal(size=(B, M)))
    mask = torch.tensor(rng.random((B, M)) < 0.7)
    fixed = torch.zeros(B, d, dtype=torch.bool)
    fixed[:4, 3:6] = True
    human = torch.tensor(rng.uniform(-0.5, 0.5, (B, d)))
    w = torch.tensor(rng.normal(size=(B, d)))
    cfg = SailConfig()
    x_imp = sail_center_implicit(a, C, c, mask, 5.0, fixed, human, cfg)
    x_unr = sail_project(a, C, c, mask, 5.0, fixed_mask=fixed, fixed_action=human, config=cfg)
    torch.testing.assert_close(x_imp, x_unr, rtol=0, atol=1e-9)
    (g_imp,) = torch.autograd.grad((w * x_imp).sum(), a)
    (g_unr,) = torch.autograd.grad((w * x_unr).sum(), a)
    torch.testing.assert_close(g_imp, g_unr, rtol=1e-7, atol=1e-9)
    assert torch.all(g_imp[fixed] == 0)                    # human blocks do not move


def gap_fd_along(m, mb, v, surrogates, split: bool, h: float = 1e-6) -> float:
    """Central finite difference of W_gap along ``v``, restricted to the split
    parameters (W, b) or to all the others; ``v`` is masked and normalized in
    place, so the caller's ``grad_w @ v`` is the matching directional derivative.
    Leaves ``m``'s parameters moved (a throwaway method)."""
    names = [n for tree in m.trees for n, _ in tree.named_parameters()]
    on = torch.cat([torch.full((p.numel(),), (n in ("W", "b")) == split, dtype=torch.bool)
                    for n, p in zip(names, m.actor_params)])
    v.copy_(torch.where(on, v, torch.zeros_like(v)))
    v /= v.norm()
    base = [p.detach().clone() for p in m.actor_params]

    def w_at(step):
        with torch.no_grad():
            for p, b, dv in zip(m.actor_params, base, unflatten_like(v, m.actor_params)):
                p.copy_(b + step * dv)
        L, team = surrogates(m, mb)
        return float(talo_gap(L, team, m.groups, with_hvp=False)[2])

    return (w_at(h) - w_at(-h)) / (2 * h)


@pytest.mark.parametrize("name", ["sage", "talo_cbf"])
def test_grad_w_gap_matches_directional_finite_difference(name):
    m, mb = prepared(name, seed=1)
    L, team = team_surrogates(m, mb)
    _, _, w0, grad_w = talo_gap(L, team, m.groups, separable=not m.uses_sail)
    assert float(w0) > 0
    # Direction over the leaf controllers and log_std only: the split parameters'
    # gradients are straight-through surrogates (Eq. st_gate), whose autograd
    # derivative is again a surrogate and not the finite-difference derivative.
    v = torch.randn(grad_w.shape, generator=torch.Generator().manual_seed(0), dtype=grad_w.dtype)
    fd = gap_fd_along(m, mb, v, team_surrogates, split=False)
    assert fd == pytest.approx(float(grad_w @ v), rel=1e-4, abs=1e-8)


def test_talo_step_decreases_gap_relative_to_independent_step():
    """First-order check on a fixed minibatch: moving along g_TALO lowers W_gap
    at rate <= -sigma*W, and faster than moving along g_ind. sigma is chosen so
    that the correction is active (Delta_gap > 0)."""
    from common.algos.talo import talo_direction, talo_gap

    m, mb = prepared("sage", seed=0)
    L, team = team_surrogates(m, mb)
    g_ind, _, w0, grad_w = talo_gap(L, team, m.groups)
    sigma = 2.0 * abs(float(grad_w @ g_ind)) / float(w0) + 1.0
    L, team = team_surrogates(m, mb)
    res = talo_direction(L, team, m.groups, sigma=sigma, eps=1e-12)
    assert res.corrected
    base = [p.detach().clone() for p in m.actor_params]

    def w_along(direction, step):
        with torch.no_grad():
            for p, b, dv in zip(m.actor_params, base, unflatten_like(direction, m.actor_params)):
                p.copy_(b + step * dv)
        L, team = team_surrogates(m, mb)
        return float(talo_gap(L, team, m.groups, with_hvp=False)[2])

    step = 1e-7 / float(res.g_ind.norm())
    rate_talo = (w_along(res.g_talo, step) - w_along(res.g_talo, -step)) / (2 * step)
    rate_ind = (w_along(res.g_ind, step) - w_along(res.g_ind, -step)) / (2 * step)
    assert rate_talo < rate_ind
    assert rate_talo <= -sigma * res.w_gap * 0.9


@pytest.mark.parametrize("name", ["happo", "happo_cbf"])
def test_happo_factor_is_product_of_updated_ratios(name):
    m, mb = prepared(name, seed=2, double=False)
    happo_step(m, mb, tau=0.5, kappa=3.0)
    order = list(m.last_happo_factors)
    assert sorted(order) == [0, 1, 2]
    assert torch.equal(m.last_happo_factors[order[0]], torch.ones_like(mb.adv))
    # identity centers: carrier j's ratio depends on theta_j only, so the final
    # parameters reproduce the ratio each carrier had right after its own step
    with torch.no_grad():
        a_st = m.proposal.tree_actions(mb, 0.5, grad=False)
        ratio = m.proposal.log_ratio(mb, m.proposal.center(mb, a_st, 3.0), m.proposal.log_std()).exp()
    expected = torch.ones_like(mb.adv, dtype=torch.float64)
    for i in order:
        torch.testing.assert_close(m.last_happo_factors[i].double(), expected, rtol=1e-6, atol=1e-9)
        expected = expected * torch.where(mb.active[:, i], ratio[:, i], torch.ones_like(ratio[:, i]))
    assert not torch.allclose(expected, torch.ones_like(expected))   # the factor is not trivial


def test_state_dict_is_weights_only_and_resumes_exactly():
    cfg = AlgoConfig(epochs=1, minibatches=2, critic_hidden=16, encoder_latent=4, critic_uses_state=True)
    a = make_method("sage", cfg, OBS, 3 * OBS)
    batch = small_batch(a)
    a.update(batch, 0.1)
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    buf.seek(0)
    state = torch.load(buf, weights_only=True)
    b = make_method("sage", AlgoConfig(epochs=1, minibatches=2, critic_hidden=16, encoder_latent=4,
                                       critic_uses_state=True, seed=7), OBS, 3 * OBS)
    b.load_state_dict(state)
    da, db = a.update(batch, 0.2), b.update(batch, 0.2)
    assert da == db
    torch.testing.assert_close(flat_params(a), flat_params(b), rtol=0, atol=0)
    for pa, pb in zip(a.critic.parameters(), b.critic.parameters()):
        torch.testing.assert_close(pa, pb, rtol=0, atol=0)
    with pytest.raises(ValueError, match="method"):
        make_method("happo", cfg, OBS, 3 * OBS).load_state_dict(state)


def test_actor_settings_schedules():
    sage, happo = make_method("sage", AlgoConfig(), OBS, 0), make_method("happo", AlgoConfig(), OBS, 0)
    s0, s1 = sage.actor_settings(0.0), sage.actor_settings(1.0)
    assert s0["kappa"] == pytest.approx(1.0) and s1["kappa"] == pytest.approx(30.0)
    assert s0["tau"] == pytest.approx(1.0) and s1["tau"] == pytest.approx(0.1)
    assert happo.actor_settings(0.5)["kappa"] == 0.0                     # identity center


@pytest.mark.parametrize("name", ["sage", "happo"])
def test_human_blocks_contribute_no_actor_loss(name):
    """Carrier 0 human-occupied everywhere: its tree receives no policy gradient."""
    m = make_method(name, AlgoConfig(ent_coef=0.0, epochs=1, minibatches=1), OBS, 0)
    task = BanditTask(obs_dim=OBS, seed=0, n_rows=10, row_frac=0.5)
    rng = np.random.default_rng(0)
    ctx_fixed = np.zeros((6, 8, 9), dtype=bool)
    ctx_fixed[..., 0:3] = True
    original = task.sample_context
    task.sample_context = lambda r, T, K: {**original(r, T, K), "fixed_mask": ctx_fixed}
    batch = collect(m, task, 6, 8, 0.5, rng)
    assert np.all(batch["logp"][..., 0] == 0.0)
    mb, _ = m._prepare(batch)
    L, team = team_surrogates(m, mb)
    g_ind, g_team, _, _ = talo_gap(L, team, m.groups, with_hvp=False)
    n0 = sum(p.numel() for p in m.groups[0])
    assert torch.all(g_ind[:n0] == 0) and torch.all(g_team[:n0] == 0)
    assert g_ind[n0:].abs().sum() > 0
    tree0 = [p.detach().clone() for p in m.groups[0]]
    m.update(batch, 0.5)
    for a, b in zip(tree0, m.groups[0]):
        torch.testing.assert_close(a, b.detach(), rtol=0, atol=0)


class SaturatedHuman(BanditTask):
    """The human plays the box faces: its measured action is exactly +-1 (the scripted
    human's clipped command reaches them), outside the proposal's open support."""

    def target(self, obs):
        return np.where(super().target(obs) >= 0, 1.0, -1.0)


@pytest.mark.parametrize("name", ALL_METHODS)
def test_human_block_on_the_box_face_updates_every_method(name):
    """Regression (`sage train --human-slot 1` raised "a_prop must be finite with |a| < 1"
    in the learner): a human block at |a| = 1 has no density and must not reach the
    log-prob; the robot carriers' ratios stay exact (on-policy: log-ratio 0 at the start)."""
    m = make_method(name, AlgoConfig(epochs=1, minibatches=2, critic_hidden=32, encoder_latent=8), OBS, 3 * OBS)
    batch = collect(m, SaturatedHuman(obs_dim=OBS, seed=1, n_rows=10, row_frac=0.5, human_rate=0.5), 6, 8, 0.5,
                    np.random.default_rng(1))
    fixed = batch["fixed_mask"]
    assert fixed.any() and np.all(np.abs(batch["a_prop"][fixed]) == 1.0)
    assert np.all(np.abs(batch["a_prop"][~fixed]) < 1.0)
    before = flat_params(m)
    diag = m.update(batch, progress=0.5)
    assert diag["logratio_at_start"] < 1e-5
    assert all(np.isfinite(v) for v in diag.values() if np.isscalar(v))
    assert not torch.equal(before, flat_params(m))
    assert torch.isfinite(flat_params(m)).all()
