"""Like-for-like mechanism metrics (ratios against the update's start, the local
claim's A/B), the direct TALO step, dense oblique trees, the Joint+CBF ablation
and HAPPO's per-update carrier order (common/algos/methods.py, diagnostics.py,
joint.py, sequential.py)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from common.algos import AlgoConfig, make_method
from common.algos.registry import ALL_METHODS, METHODS, method_spec
from common.algos.synthetic import BanditTask, collect
from common.algos.diagnostics import gap_summary
from common.algos.joint import joint_step
from common.algos.talo import cosine, flat_grad, talo_gap, talo_project, unflatten_like
from common.policy.proposal import proposal_log_prob
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
    a_st = m.proposal.tree_actions(mb, tau, grad=True)
    log_ratio = m.proposal.log_ratio(mb, m.proposal.center(mb, a_st, kappa), m.proposal.log_std())
    return m.proposal.surrogates(mb, log_ratio)


def start_surrogates(m, mb, tau=TAU, kappa=KAPPA):
    """The diagnostics' surrogates at the current parameters when they are the update's
    start: the ratio against the forward itself (exactly 1)."""
    a_st = m.proposal.tree_actions(mb, tau, grad=True)
    logp = proposal_log_prob(m.proposal.center(mb, a_st, kappa), m.proposal.log_std(), mb.a_prop)
    return m.proposal.surrogates(mb, m.proposal.ratio_against(mb, logp, logp.detach()))


def lagged_batch(m, seed=0):
    """A batch its method is two updates past (the behaviour policy lags the learner)."""
    batch = small_batch(m, seed=seed)
    for k in range(2):
        m.update(small_batch(m, seed=100 + k), 0.5)
    return batch


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


def test_the_registry_names_the_update_step_the_learner_runs():
    from common.algos.joint import joint_step
    from common.algos.registry import MethodSpec
    from common.algos.sequential import sequential_step

    for name in ALL_METHODS:
        m = make_method(name, small_cfg(), OBS, 0)
        want = joint_step if method_spec(name).step == "joint" else sequential_step
        assert m.update_step is want and m.joint_step == (method_spec(name).step == "joint")
    with pytest.raises(ValueError, match="step must be one of"):
        MethodSpec("x", "X", shielded=True, uses_sail=False, uses_talo=False, step="parallel")
    with pytest.raises(ValueError, match="TALO is a joint step"):
        MethodSpec("x", "X", shielded=True, uses_sail=False, uses_talo=True, step="sequential")
    with pytest.raises(ValueError):
        AlgoConfig(happo_order="epoch")
    with pytest.raises(ValueError):
        AlgoConfig(talo_eta=0.0)


# --------------------------------------------------------------------------- W_gap at one point

@pytest.mark.parametrize("pair", [("sage", "sail_cbf"), ("talo_cbf", "happo_cbf"),
                                  ("joint_cbf", "happo")])
def test_w_gap_first_is_measured_at_the_same_point(pair):
    """Same batch, same initial parameters: a joint (TALO) and a sequential method
    report the same W_gap / cos on the first minibatch, before any step, with the
    ratios against the update's start (exactly 1 there)."""
    a, b, ref = (make_method(n, small_cfg(), OBS, 0) for n in pair + pair[:1])
    torch.testing.assert_close(flat(a), flat(b), rtol=0, atol=0)
    batch = small_batch(a)
    mb = first_minibatch(ref, batch)
    s = ref.actor_settings(0.5)
    L, team = start_surrogates(ref, mb, tau=s["tau"], kappa=s["kappa"])
    g_ind, g_team, w_ref, _ = talo_gap(L, team, ref.groups, with_hvp=False)
    da, db = a.update(batch, 0.5), b.update(batch, 0.5)
    for d in (da, db):
        assert d["w_gap_first"] == pytest.approx(float(w_ref), rel=1e-6, abs=1e-12)
        assert d["cos_ind_team_first"] == pytest.approx(cosine(g_ind, g_team), abs=1e-6)
        assert d["logratio_at_start"] < 1e-5    # collected by these very parameters
    if a.uses_sail:
        # SAIL couples the carriers: the gap is there before any step
        assert float(w_ref) > 1e-6
    else:
        # identity center at ratio 1: L_team's gradient is sum_i grad rho_i = g_ind
        assert float(w_ref) == 0.0 and da["w_gap_first"] == db["w_gap_first"] == 0.0
    # later minibatches are off the start point: the mean is over steps taken
    assert da["w_gap_mean"] > da["w_gap_first"] and db["w_gap_mean"] > db["w_gap_first"]


@pytest.mark.parametrize("name", ALL_METHODS)
def test_w_gap_first_is_exactly_zero_at_the_update_start_whatever_the_lag(name):
    """The diagnostics divide by the policy at the update's start, not by the behaviour
    policy: on a batch the learner is two updates past (ratios against the behaviour
    policy far from 1) the first minibatch still sits at ratio 1, so W_gap is exactly 0
    there for every method without SAIL's coupling, and grows over the epochs."""
    m = make_method(name, small_cfg(), OBS, 0)
    d = m.update(lagged_batch(m), 0.5)
    assert d["logratio_at_start"] > 1e-3                     # the lag is real
    if method_spec(name).uses_sail:
        assert d["w_gap_first"] > 1e-6
    else:
        assert d["w_gap_first"] == 0.0
        assert d["cos_ind_team_first"] == pytest.approx(1.0, abs=1e-6)   # g_team = g_ind
    n = m.cfg.epochs * m.cfg.minibatches
    assert [d[f"w_gap_mb{k}"] for k in range(n)][0] == d["w_gap_first"] and f"w_gap_mb{n}" not in d
    assert all(d[f"w_gap_mb{k}"] > 0 for k in range(1, n))
    assert d["w_gap_median"] > 0 and d["w_gap_geomean"] > 0
    for key in ("w_gap_first", "w_gap_median", "w_gap_geomean", "w_gap_mean", "cos_ind_team_median",
                "cos_ind_team_first", "cos_ind_team_mean", "ab_w_before", "ab_w_talo", "ab_w_ind"):
        assert np.isfinite(d[key]), key


def test_the_ppo_surrogate_keeps_the_behaviour_ratio():
    """Only the diagnostics change reference: on a lagged batch the step taken is the one
    the behaviour-ratio surrogates give (Joint+CBF, direct: delta = eta (g_ind + entropy))."""
    m = make_method("joint_cbf", small_cfg(talo_step="direct"), OBS, 0)
    batch = lagged_batch(m)
    m.policy.double()
    mb, _ = m._prepare(batch)
    L, team = surrogates(m, mb)      # ratios against the stored logp (the behaviour policy)
    g = talo_gap(L, team, m.groups, separable=True, with_hvp=False)[0] \
        + m.cfg.ent_coef * flat_grad(m.proposal.entropy().sum(), m.actor_params)
    before = flat(m)
    _, gap = joint_step(m, mb, TAU, KAPPA)
    torch.testing.assert_close(flat(m) - before, m.cfg.talo_eta * g, rtol=1e-9, atol=1e-12)
    assert gap.w_gap == 0.0       # while the diagnostics were taken at ratio 1


@pytest.mark.parametrize("name", ["talo_cbf", "sail_cbf"])
def test_on_policy_the_diagnostics_share_the_algorithms_surrogates(name):
    """Where the update's start is the behaviour policy bitwise (on-policy: the actors'
    log-density is the learner's), the two surrogates are one object and the joint step
    computes one gap; with a lag they are two, and differ."""
    m = make_method(name, small_cfg(), OBS, 0)
    fresh, _ = m._prepare(small_batch(m))
    kappa = m.actor_settings(0.5)["kappa"]
    # the in-process actors give the learner's log-density bitwise (the sample-based bandit
    # here rounds differently in the last bits): make the stored one exactly that
    fresh.logp_old = torch.where(fresh.active, m.proposal.start_log_prob(fresh, TAU, kappa), fresh.logp_old)
    _, _, behaviour, start = m.proposal.start_point(fresh, TAU, kappa)
    assert start is behaviour
    fresh.logp_old = fresh.logp_old + 1e-12 * fresh.active           # one ulp-ish apart: two surrogates
    _, _, behaviour, start = m.proposal.start_point(fresh, TAU, kappa)
    assert start is not behaviour
    lagged, _ = m._prepare(lagged_batch(m))
    _, _, behaviour, start = m.proposal.start_point(lagged, TAU, kappa)
    assert start is not behaviour and not torch.equal(start.log_ratio, behaviour.log_ratio)
    assert float(start.log_ratio.detach().abs().max()) == 0.0  # the forward is its own reference


def test_w_gap_mean_is_measured_before_each_step():
    """A sequential method's per-minibatch W_gap is taken at the parameters its step starts from."""
    m, ref = (make_method("sail_cbf", small_cfg(epochs=1, minibatches=1), OBS, 0) for _ in range(2))
    batch = small_batch(m)
    mb = first_minibatch(ref, batch)
    s = ref.actor_settings(0.5)
    L, team = start_surrogates(ref, mb, tau=s["tau"], kappa=s["kappa"])
    w_ref = float(talo_gap(L, team, ref.groups, with_hvp=False)[2])
    d = m.update(batch, 0.5)
    assert d["w_gap_mean"] == pytest.approx(w_ref, rel=1e-6) == d["w_gap_first"]
    assert np.isnan(d["w_gap_geomean"])          # no minibatch after the first


def test_gap_summary_medians_and_log_means():
    w = [0.0, 1e-4, 1e-2, 1.0, 1e3]              # a heavy tail: the mean is the outlier's
    cos = [1.0, 0.9, 0.5, -0.2, 0.8]
    out = gap_summary(w, cos)
    assert out["w_gap_first"] == 0.0 and out["w_gap_last"] == 1e3
    assert out["w_gap_median"] == 1e-2 and out["w_gap_mean"] == pytest.approx(sum(w) / 5)
    assert out["w_gap_geomean"] == pytest.approx((1e-4 * 1e-2 * 1.0 * 1e3) ** 0.25)   # = 0.1
    assert out["cos_ind_team_median"] == 0.8 and out["cos_ind_team_mean"] == pytest.approx(0.6)
    assert [out[f"w_gap_mb{k}"] for k in range(5)] == w
    assert [out[f"cos_ind_team_mb{k}"] for k in range(5)] == cos
    assert out["w_gap"] == out["w_gap_mean"] and out["cos_ind_team"] == out["cos_ind_team_mean"]
    assert gap_summary([1.0, 0.0, 2.0], [1.0] * 3)["w_gap_geomean"] == 0.0   # a step at W = 0


# --------------------------------------------------------------------------- the local claim's A/B

@pytest.mark.parametrize("name", ["sage", "happo_cbf"])
def test_local_ab_is_deterministic_and_leaves_the_parameters(name):
    """The A/B on a frozen minibatch: the same numbers twice, the parameters untouched,
    and each arm equals W_gap recomputed by hand at theta + length g / ||g||."""
    m = make_method(name, small_cfg(), OBS, 0)
    batch = lagged_batch(m)
    m.policy.double()
    mb, _ = m._prepare(batch)
    mb.logp_start = m.proposal.start_log_prob(mb, TAU, KAPPA)
    theta0 = flat(m)
    with torch.no_grad():               # move off the start, as the last minibatch of an update is
        for p in m.actor_params:
            p.add_(0.02 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel()),
                                      dtype=p.dtype))
    at = flat(m)
    a_st, _, _, start = m.proposal.start_point(mb, TAU, KAPPA)
    g_ind, _, w0, grad_w = m.proposal.gap(a_st, start, with_hvp=True)
    m.cfg.talo_sigma = 2.0 * abs(float(grad_w @ g_ind)) / float(w0) + 1.0   # forces Delta_gap > 0
    length = 0.05
    first, second = m.local_ab(mb, TAU, KAPPA, length), m.local_ab(mb, TAU, KAPPA, length)
    assert first == second
    torch.testing.assert_close(flat(m), at, rtol=0, atol=0)
    assert first["ab_step"] == length and first["ab_w_before"] > 0 and first["ab_corrected"] == 1.0
    assert first["ab_ratio"] == pytest.approx(first["ab_w_talo"] / first["ab_w_ind"])
    # first order, by construction of Eq. (talo_projection): g_TALO's rate meets the condition
    g_talo_n = float(talo_project(g_ind, grad_w, w0, m.cfg.talo_sigma, m.cfg.talo_eps)[0].norm())
    assert first["ab_rate_talo"] <= -m.cfg.talo_sigma * float(w0) / g_talo_n * (1 - 1e-6)
    assert first["ab_rate_ind"] == pytest.approx(float(grad_w @ g_ind / g_ind.norm()), rel=1e-9)
    assert first["ab_rate_talo"] < first["ab_rate_ind"]

    def w_here():
        a_st, _, _, start = m.proposal.start_point(mb, TAU, KAPPA)
        return m.proposal.gap(a_st, start, with_hvp=False)

    g_talo, _ = talo_project(g_ind, grad_w, w0, m.cfg.talo_sigma, m.cfg.talo_eps)
    assert float(w0) == first["ab_w_before"]
    for g, key in ((g_talo, "ab_w_talo"), (g_ind, "ab_w_ind")):
        with torch.no_grad():
            for p, d in zip(m.actor_params, unflatten_like(at + length * g / g.norm(), m.actor_params)):
                p.copy_(d)
        assert float(w_here()[2]) == pytest.approx(first[key], rel=1e-12)
    # at the start point itself the identity center has nothing to regulate
    with torch.no_grad():
        for p, d in zip(m.actor_params, unflatten_like(theta0, m.actor_params)):
            p.copy_(d)
    if not m.uses_sail:
        at_start = m.local_ab(mb, TAU, KAPPA, length)
        assert at_start["ab_w_before"] == 0.0 and at_start["ab_corrected"] == 0.0
        assert at_start["ab_w_talo"] == at_start["ab_w_ind"] and at_start["ab_ratio"] == 1.0


@pytest.mark.parametrize("name", ["happo", "sail_cbf", "talo_cbf", "sage", "joint_cbf"])
@pytest.mark.parametrize("on_policy", [True, False])
def test_the_ab_reads_the_steps_forward_to_the_same_bits(name, on_policy):
    """``local_ab`` given the update step's ``GapAtStart`` (what ``Method.update`` passes:
    the forward, and on-policy a TALO method's grad W, at the parameters before the step)
    answers what it answers from a forward of its own, bit for bit."""
    m = make_method(name, small_cfg(), OBS, 0)
    mb, _ = m._prepare(small_batch(m) if on_policy else lagged_batch(m))
    mb = m.proposal.prepared(mb)
    kappa = m.actor_settings(0.5)["kappa"]
    if on_policy:   # the stored log-density exactly the learner's (see the test above)
        mb.logp_old = torch.where(mb.active, m.proposal.start_log_prob(mb, TAU, kappa), mb.logp_old)
    mb.logp_start = m.proposal.start_log_prob(mb, TAU, kappa)
    with torch.no_grad():               # off the start, as the last minibatch of an update is
        for p in m.actor_params:
            p.add_(0.02 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel()),
                                      dtype=p.dtype))
    before = [p.detach().clone() for p in m.actor_params]
    _, gap = m.update_step(m, mb, TAU, kappa)
    assert gap.reusable
    assert (gap.grad_w is not None) == (on_policy and m.joint_step and m.uses_talo)
    reused = m.local_ab(mb, TAU, kappa, 0.05, at=before, gap=gap)
    fresh = m.local_ab(mb, TAU, kappa, 0.05, at=before)
    assert reused.keys() == fresh.keys()
    for key, value in fresh.items():
        assert reused[key] == value or (np.isnan(value) and np.isnan(reused[key])), key


def test_update_logs_the_ab_on_its_last_minibatch():
    m = make_method("talo_cbf", small_cfg(), OBS, 0)
    d = m.update(lagged_batch(m), 0.5)
    for key in ("ab_w_before", "ab_w_talo", "ab_w_ind", "ab_ratio", "ab_rate_talo", "ab_rate_ind",
                "ab_corrected", "ab_step"):
        assert np.isfinite(d[key]), key
    assert d["ab_step"] > 0        # the length of the method's own last step (mech_ab_step = 0)
    fixed = make_method("talo_cbf", small_cfg(mech_ab_step=0.01), OBS, 0)
    assert fixed.update(small_batch(fixed), 0.5)["ab_step"] == 0.01
    # one minibatch: the A/B's point is the update's start, and its steps are measured
    # against that start (not each against itself, which would read 0 for the identity center)
    one = make_method("happo_cbf", small_cfg(epochs=1, minibatches=1), OBS, 0)
    d1 = one.update(lagged_batch(one), 0.5)
    assert d1["ab_w_before"] == d1["w_gap_first"] == 0.0 and d1["ab_corrected"] == 0.0
    assert d1["ab_w_ind"] == d1["ab_w_talo"] > 0 and d1["ab_ratio"] == 1.0
    off = make_method("talo_cbf", small_cfg(mech_ab_every=0), OBS, 0)
    assert "ab_ratio" not in off.update(small_batch(off), 0.5)
    with pytest.raises(ValueError):
        AlgoConfig(mech_ab_step=-1.0)
    with pytest.raises(ValueError):
        AlgoConfig(mech_ab_every=-1)


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
    g_ent = m.cfg.ent_coef * flat_grad(m.proposal.entropy().sum(), m.actor_params)
    w_start = float(talo_gap(*start_surrogates(m, mb), m.groups, with_hvp=False)[2])
    before = flat(m)
    stats, gap = joint_step(m, mb, TAU, KAPPA)
    delta = flat(m) - before
    assert stats["delta_gap"] > 0 and stats["talo_corrected"] == 1.0
    assert gap.w_gap == pytest.approx(w_start, rel=1e-12)    # the diagnostics: ratio 1 at theta_0
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


@pytest.mark.parametrize("name", ["talo_cbf", "sage", "joint_cbf"])
@pytest.mark.parametrize("step", ["adam", "direct"])
def test_both_talo_steps_are_selectable(name, step):
    """The joint methods apply g per ``talo_step``; the direct step (the paper's
    theta <- theta + eta g_TALO) meets Eq. (talo_condition) on every minibatch."""
    m = make_method(name, small_cfg(talo_step=step), OBS, 0)
    assert m.cfg.talo_step == step
    before = flat(m)
    d = m.update(lagged_batch(m), 0.5)
    assert not torch.equal(before, flat(m))
    if m.uses_talo:
        assert (d["talo_condition_met"] == 1.0) if step == "direct" else (0.0 <= d["talo_condition_met"] <= 1.0)
    else:
        assert "talo_condition_met" not in d
    assert AlgoConfig().talo_step == "adam"    # the default is not changed silently: protocols pin it


@pytest.mark.parametrize("name", ALL_METHODS)
def test_dense_oblique_trees_train_with_every_method(name):
    """split_k = 0: every split vector is dense over the observation and routes by
    w_k.o / ||w_k|| (Eq. hard_gate) in what the actors run; every method trains on it."""
    from common.policy.tree_torch import TeamPolicy

    m = make_method(name, small_cfg(split_k=0, talo_step="direct"), OBS, 0)
    d = m.update(lagged_batch(m), 0.5)
    assert all(np.isfinite(v) for k, v in d.items() if not k.startswith("ab_ratio")), name
    params = m.policy_params()
    for i in range(3):
        W = params[f"carrier_{i}/W"]
        assert (W != 0).all() and W.shape[1] == OBS                   # oblique: all features
    # the split parameters moved (dense straight-through gradient reaches every weight)
    W_now = torch.cat([t.W.detach().reshape(-1) for t in m.trees])
    W_init = torch.cat([t.W.detach().reshape(-1) for t in make_method(name, small_cfg(split_k=0), OBS, 0).trees])
    assert (W_now != W_init).float().mean() > 0.5
    # the exported (actor) forward routes as the learner does, on the normalized vectors
    obs = torch.randn(32, 3, OBS, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        torch.testing.assert_close(TeamPolicy.from_params(params).double()(obs.double()).action,
                                   m.policy.double()(obs.double()).action, rtol=1e-5, atol=1e-6)
    sparse = make_method(name, small_cfg(split_k=1), OBS, 0).policy_params()["carrier_0/W"]
    assert ((sparse != 0).sum(axis=1) == 1).all()                 # the contrast: k = 1 is axis-aligned


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
    g = g_ind + j.cfg.ent_coef * flat_grad(j.proposal.entropy().sum(), j.actor_params)
    before = flat(j)
    joint_step(j, mb, TAU, KAPPA)
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
@pytest.mark.sweep
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
