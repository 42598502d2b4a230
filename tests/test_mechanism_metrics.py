"""Like-for-like mechanism metrics, the direct TALO step, the Joint+CBF ablation
and HAPPO's per-update carrier order (common/algos/methods.py)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from common.algos import AlgoConfig, make_method
from common.algos.registry import ALL_METHODS, METHODS, method_spec
from common.algos.synthetic import BanditTask, collect
from common.algos.talo import cosine, flat_grad, talo_gap, talo_project
from common.shield.qp import solve_cbf_qp

OBS = 6
TAU, KAPPA = 0.5, 3.0

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def small_cfg(**kw):
    return AlgoConfig(**{"epochs": 2, "minibatches": 2, "critic_hidden": 16, "encoder_latent": 4, **kw})


def small_batch(method, seed=0, T=6, K=8, human_rate=0.2, progress=0.5):
    task = BanditTask(obs_dim=OBS, seed=seed, n_rows=10, row_frac=0.5, human_rate=human_rate)
    return collect(method, task, T, K, progress, np.random.default_rng(seed))


def flat(m):
    return torch.cat([p.detach().reshape(-1) for p in m.actor_params]).clone()


def surrogates(m, mb, tau=TAU, kappa=KAPPA):
    a_st = m._tree_actions(mb, tau, grad=True)
    log_ratio = m._log_ratio(mb, m._center(mb, a_st, kappa), m._log_std())
    return m._surrogates(mb, log_ratio)


def first_minibatch(m, batch):
    """The first minibatch update() will draw (same generator seed, before any draw).
    ``_prepare`` moves the value normalizer: call it on a fresh twin, not on the
    method whose update is checked."""
    data, _ = m._prepare(batch)
    gen = torch.Generator().manual_seed(m.cfg.seed + 1)
    perm = torch.randperm(data.obs.shape[0], generator=gen)
    return data.index(torch.tensor_split(perm, min(m.cfg.minibatches, len(perm)))[0])


# --------------------------------------------------------------------------- registry

def test_registry_has_the_ablation_arm():
    spec = method_spec("joint_cbf")
    assert spec.title == "Joint+CBF"
    assert spec.shielded and not spec.uses_sail and not spec.uses_talo and spec.joint_step
    assert "joint_cbf" in ALL_METHODS and "joint_cbf" not in METHODS   # Table I stays five
    for name in ALL_METHODS:
        s = method_spec(name)
        assert s.joint_step == (name in ("talo_cbf", "sage", "joint_cbf"))
    # joint_cbf differs from talo_cbf in the projection only
    t, j = method_spec("talo_cbf"), method_spec("joint_cbf")
    assert (t.shielded, t.uses_sail, t.joint_step) == (j.shielded, j.uses_sail, j.joint_step)
    with pytest.raises(ValueError):
        AlgoConfig(talo_step="sgd")
    with pytest.raises(ValueError):
        AlgoConfig(happo_order="epoch")
    with pytest.raises(ValueError):
        AlgoConfig(talo_eta=0.0)


# --------------------------------------------------------------------------- W_gap at one point

@pytest.mark.parametrize("pair", [("sage", "sail_cbf"), ("talo_cbf", "happo_cbf"),
                                  ("joint_cbf", "happo")])
def test_w_gap_first_is_measured_at_the_same_point(pair):
    """Same batch, same initial parameters: a joint (TALO) and a sequential method
    report the same W_gap / cos on the first minibatch, before any step."""
    a, b, ref = (make_method(n, small_cfg(), OBS, 0) for n in pair + pair[:1])
    torch.testing.assert_close(flat(a), flat(b), rtol=0, atol=0)
    batch = small_batch(a)
    mb = first_minibatch(ref, batch)
    s = ref.actor_settings(0.5)
    L, team = surrogates(ref, mb, tau=s["tau"], kappa=s["kappa"])
    g_ind, g_team, w_ref, _ = talo_gap(L, team, ref.groups, with_hvp=False)
    da, db = a.update(batch, 0.5), b.update(batch, 0.5)
    for d in (da, db):
        assert d["w_gap_first"] == pytest.approx(float(w_ref), rel=1e-6, abs=1e-12)
        assert d["cos_ind_team_first"] == pytest.approx(cosine(g_ind, g_team), abs=1e-6)
        assert d["logratio_at_start"] < 1e-5
    if a.uses_sail:
        # SAIL couples the carriers: the gap is there before any step
        assert float(w_ref) > 1e-6
    else:
        # identity center, on-policy: rho = 1 and L_team's gradient is sum_i grad rho_i,
        # so g_team = g_ind and W_gap is 0 up to rounding on the first minibatch
        assert float(w_ref) < 1e-10
    # later minibatches are off-policy: the mean is over steps taken
    assert da["w_gap_mean"] > da["w_gap_first"] and db["w_gap_mean"] > db["w_gap_first"]


def test_w_gap_mean_is_measured_before_each_step():
    """A sequential method's per-minibatch W_gap is taken at the parameters its step starts from."""
    m, ref = (make_method("sail_cbf", small_cfg(epochs=1, minibatches=1), OBS, 0) for _ in range(2))
    batch = small_batch(m)
    mb = first_minibatch(ref, batch)
    s = ref.actor_settings(0.5)
    L, team = surrogates(ref, mb, tau=s["tau"], kappa=s["kappa"])
    w_ref = float(talo_gap(L, team, ref.groups, with_hvp=False)[2])
    d = m.update(batch, 0.5)
    assert d["w_gap_mean"] == pytest.approx(w_ref, rel=1e-6) == d["w_gap_first"]


# --------------------------------------------------------------------------- direct TALO step

def prepared_double(name, **cfg):
    m = make_method(name, AlgoConfig(**cfg), OBS, 0)
    batch = small_batch(m, seed=1)
    m.policy.double()
    mb, _ = m._prepare(batch)
    return m, mb


def test_direct_talo_step_meets_descent_condition():
    """Frozen minibatch: the applied direct step delta satisfies Eq. (talo_condition)
    to first order, grad W(theta_0) . delta <= -sigma W eta, with the correction
    active and the entropy term included; no clipping after the projection."""
    m, mb = prepared_double("sage", talo_step="direct", talo_eta=0.05, max_grad_norm=1e-6)
    L, team = surrogates(m, mb)
    g_ind, _, w0, grad_w = talo_gap(L, team, m.groups)
    sigma = 2.0 * abs(float(grad_w @ g_ind)) / float(w0) + 1.0       # forces Delta_gap > 0
    m.cfg.talo_sigma = sigma
    # the entropy gradient (log_std only) at theta_0
    g_ent = m.cfg.ent_coef * flat_grad(m._entropy().sum(), m.actor_params)
    before = flat(m)
    stats, gap = m._joint_step(mb, TAU, KAPPA)
    delta = flat(m) - before
    assert stats["delta_gap"] > 0 and stats["talo_corrected"] == 1.0
    assert gap["w_gap"] == pytest.approx(float(w0), rel=1e-12)
    eta = m.cfg.talo_eta
    assert float(grad_w @ delta) <= -sigma * float(w0) * eta + 1e-8
    assert stats["talo_condition_met"] == 1.0 and stats["talo_step_decreases_gap"] == 1.0
    # the step is eta * g_TALO with the entropy gradient inside g_ind (no clipping to 1e-6)
    g_talo, _ = talo_project(g_ind + g_ent, grad_w, w0, sigma, m.cfg.talo_eps)
    torch.testing.assert_close(delta, eta * g_talo, rtol=1e-9, atol=1e-12)
    assert float(delta.norm()) > 1e3 * m.cfg.max_grad_norm * eta


def test_direct_talo_update_logs_condition_met():
    m = make_method("sage", small_cfg(talo_step="direct"), OBS, 0)
    d = m.update(small_batch(m), 0.5)
    assert d["talo_condition_met"] == 1.0
    for key in ("talo_step_decreases_gap", "talo_gap_at_floor", "delta_gap", "talo_corrected"):
        assert np.isfinite(d[key]), key
    adam = make_method("sage", small_cfg(), OBS, 0)
    assert 0.0 <= adam.update(small_batch(adam), 0.5)["talo_condition_met"] <= 1.0


# --------------------------------------------------------------------------- Joint+CBF

def test_joint_cbf_update_runs_and_steps_along_g_ind():
    m = make_method("joint_cbf", small_cfg(), OBS, 0)
    batch = small_batch(m)
    before = flat(m)
    d = m.update(batch, 0.5)
    assert not torch.equal(before, flat(m))
    assert m.shielded and m.joint_step and not m.uses_talo and not m.uses_sail
    assert m.actor_settings(0.5)["kappa"] == 0.0
    assert "talo_condition_met" not in d and "delta_gap" not in d and "happo_factor_std" not in d
    assert all(np.isfinite(v) for v in d.values())
    # direct variant on a frozen minibatch: delta = eta (g_ind + entropy gradient), no projection
    j, mb = prepared_double("joint_cbf", talo_step="direct", talo_eta=0.05)
    L, team = surrogates(j, mb)
    g_ind = talo_gap(L, team, j.groups, separable=True, with_hvp=False)[0]
    g = g_ind + j.cfg.ent_coef * flat_grad(j._entropy().sum(), j.actor_params)
    before = flat(j)
    j._joint_step(mb, TAU, KAPPA)
    torch.testing.assert_close(flat(j) - before, 0.05 * g, rtol=1e-9, atol=1e-12)


def test_joint_cbf_and_talo_cbf_share_the_base_scheme():
    """Where there is nothing to correct TALO+CBF's step is Joint+CBF's step: one
    on-policy minibatch with the identity center has W_gap = 0 (up to rounding,
    where talo_eps switches the correction off)."""
    cfg = small_cfg(epochs=1, minibatches=1, talo_sigma=0.0)
    t, j = make_method("talo_cbf", cfg, OBS, 0), make_method("joint_cbf", cfg, OBS, 0)
    batch = small_batch(t)
    dt = t.update(batch, 0.5)
    j.update(batch, 0.5)
    assert dt["w_gap_first"] < 1e-10 and dt["talo_gap_at_floor"] == 1.0
    torch.testing.assert_close(flat(t), flat(j), rtol=1e-6, atol=1e-7)


# --------------------------------------------------------------------------- HAPPO order

@pytest.mark.parametrize("name", ["happo", "sail_cbf"])
def test_happo_order_is_drawn_once_per_update(name):
    m = make_method(name, small_cfg(epochs=3, minibatches=4), OBS, 0)
    batch = small_batch(m)
    orders = []
    for _ in range(4):
        m.update(batch, 0.5)
        assert len(m.last_happo_orders) == 12
        assert all(o == m.last_happo_orders[0] for o in m.last_happo_orders)
        assert sorted(m.last_happo_orders[0]) == [0, 1, 2]
        orders.append(tuple(m.last_happo_orders[0]))
    per_mb = make_method(name, small_cfg(epochs=3, minibatches=4, happo_order="minibatch"), OBS, 0)
    per_mb.update(batch, 0.5)
    assert len({tuple(o) for o in per_mb.last_happo_orders}) > 1


# --------------------------------------------------------------------------- action diagnostics

def test_action_diagnostics_by_row_kind_and_qp_correction():
    m = make_method("happo_cbf", small_cfg(epochs=1, minibatches=1, diag_qp_samples=10_000), OBS, 0)
    batch = small_batch(m)
    T, K, M = batch["row_mask"].shape
    B = T * K
    flat_rows = {k: np.asarray(batch[k]).reshape(B, *np.shape(batch[k])[2:])
                 for k in ("a_st", "a_prop", "C", "c", "row_mask", "fixed_mask")}
    # shield the proposals, as a shielded actor does
    q = solve_cbf_qp(flat_rows["a_prop"], flat_rows["C"], flat_rows["c"], flat_rows["row_mask"],
                     flat_rows["fixed_mask"])
    batch["a_exec"] = q.a_exec.reshape(T, K, -1)
    kind = np.zeros(M, dtype=np.int64)
    kind[M // 3:2 * M // 3], kind[2 * M // 3:] = 1, 2
    d_plain = m.update(batch, 0.5)
    assert "proposal_violation_formation" not in d_plain          # no row kinds: "any row" only
    d = m.update(dict(batch, row_kind=kind), 0.5)
    kinds = [d[f"proposal_violation_{k}"] for k in ("carrier_wall", "payload_wall", "formation")]
    assert max(kinds) <= d["proposal_violation_rate"] <= sum(kinds) + 1e-12
    assert max(kinds[:2]) <= d["proposal_violation_any_wall"] <= sum(kinds[:2]) + 1e-12
    assert d["proposal_violation_rate"] > 0
    # a profile without formation rows ("paper"): no formation key
    d_paper = m.update(dict(batch, row_kind=np.minimum(kind, 1)), 0.5)
    assert "proposal_violation_formation" not in d_paper
    assert d_paper["proposal_violation_any_wall"] == d_paper["proposal_violation_rate"]
    # correction_st = deployment's ||Q(a_ST) - a_ST|| (all samples here)
    q_st = solve_cbf_qp(flat_rows["a_st"], flat_rows["C"], flat_rows["c"], flat_rows["row_mask"],
                        flat_rows["fixed_mask"])
    assert d["correction_st"] == pytest.approx(float(q_st.correction_norm.mean()), rel=1e-9)
    assert d["exec_minus_prop"] == pytest.approx(float(q.correction_norm.mean()), rel=1e-9)
    assert d["sail_residual"] == 0.0                              # identity center
    a_st, a_exec = flat_rows["a_st"], q.a_exec
    assert d["correction_mean"] == pytest.approx(float(np.linalg.norm(a_exec - a_st, axis=1).mean()))
    # the subsample: evenly spaced, at most diag_qp_samples problems
    few = make_method("happo_cbf", small_cfg(epochs=1, minibatches=1, diag_qp_samples=7), OBS, 0)
    assert np.isfinite(few.update(batch, 0.5)["correction_st"])
    off = make_method("happo_cbf", small_cfg(epochs=1, minibatches=1, diag_qp_samples=0), OBS, 0)
    assert "correction_st" not in off.update(batch, 0.5)


def test_grad_w_along_split_parameters_is_a_surrogate():
    """talo.py's docstring: along W, b (hard routing, straight-through backward)
    grad W_gap does not match a finite difference of W_gap; along the smooth
    parameters it does (tests/test_algos.py)."""
    from test_algos import gap_fd_along

    m, mb = prepared_double("sage")
    L, team = surrogates(m, mb)
    _, _, _, grad_w = talo_gap(L, team, m.groups)
    v = torch.randn(grad_w.shape, generator=torch.Generator().manual_seed(0), dtype=grad_w.dtype)
    fd = gap_fd_along(m, mb, v, surrogates, split=True)
    assert abs(float(grad_w @ v)) > 1e-5
    assert fd != pytest.approx(float(grad_w @ v), rel=0.5)
