"""The closed-form surrogate chain (common/algos/surrogate_chain.py) against its reference,
the same function as an autograd graph: values, log-ratios, gradients and Hessian-vector
products on constructed inputs that reach every branch (clipped and unclipped ratios, ties,
human blocks, centers beyond the atanh clip, SAIL's and the identity center), and TALO's
whole gap (g_ind, g_team, W_gap, grad W) on learner minibatches of every method."""
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from common.algos import surrogate_chain
from common.algos.config import AlgoConfig
from common.algos.methods import make_method
from common.algos.surrogate_chain import chain_surrogates, clipped, reference_surrogates
from common.algos.surrogate_kernels import ACT, _slope
from common.algos.synthetic import BanditTask, collect
from common.policy.sail import SailStep
from common.spec import CARRIER_ACT_DIM

B, N, D = 64, 3, 9


def _rel(a, b):
    return float((a - b).abs().max() / b.abs().max().clamp(min=1e-300))


def _inputs(seed, sail, dtype=torch.float32):
    gen = torch.Generator().manual_seed(seed)

    def randn(*shape, scale=1.0):
        return scale * torch.randn(*shape, generator=gen, dtype=torch.float64)

    fixed_carrier = torch.rand(B, N, generator=gen) < 0.2                       # human blocks
    fixed = fixed_carrier.repeat_interleave(3, dim=1)
    a_prop = torch.tanh(randn(B, D, scale=1.5)).float().double()
    a_st = (1.1 * torch.tanh(randn(B, D, scale=2.0))).to(dtype).requires_grad_(True)  # some beyond the clip
    log_std = randn(D, scale=0.3).sub(0.5).to(dtype).requires_grad_(True)
    active = ~fixed_carrier
    logp_old = randn(B, N, scale=2.0) - 3.0
    adv = randn(B)
    adv[:4] = 0.0                                                                # ties of the minimum
    mb = SimpleNamespace(fixed=fixed, a_prop=a_prop, a_robot=torch.where(fixed, torch.zeros_like(a_prop), a_prop),
                         adv=adv, active=active, density_terms=None)
    step = None
    if sail:
        M = randn(B, D, D, scale=0.3)
        H = torch.eye(D, dtype=torch.float64) + M @ M.transpose(1, 2)
        step = SailStep(x_star=randn(B, D, scale=0.5), H_inv=torch.linalg.inv(H), offset=randn(B, D, scale=0.5))
    return a_st, log_std, mb, step, logp_old


def _derivatives(fn, a_st, log_std, mb, step, references, seed):
    values, log_ratios = fn(a_st, log_std, mb, step, references, 0.2)
    gen = torch.Generator().manual_seed(seed)
    cot = torch.randn(values.shape, generator=gen, dtype=torch.float64)
    ga, gs = torch.autograd.grad((values * torch.sin(values) * cot).sum(), [a_st, log_std], create_graph=True)
    va = torch.randn(ga.shape, generator=gen, dtype=torch.float64).to(ga.dtype)
    vs = torch.randn(gs.shape, generator=gen, dtype=torch.float64).to(gs.dtype)
    ha, hs = torch.autograd.grad((ga * va).sum() + (gs * vs).sum(), [a_st, log_std])
    return values.detach(), log_ratios, ga.detach(), gs.detach(), ha, hs


@pytest.mark.parametrize("sail", [True, False])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_chain_matches_the_autograd_graph(sail, dtype):
    a_st, log_std, mb, step, logp_old = _inputs(3, sail, dtype)
    start = logp_old + 0.3 * torch.randn(B, N, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    for references in ((logp_old, None), (logp_old, start)):
        fast = _derivatives(chain_surrogates, a_st, log_std, mb, step, references, seed=5)
        ref = _derivatives(reference_surrogates, a_st, log_std, mb, step, references, seed=5)
        assert torch.equal(fast[1], ref[1])                       # log-ratios: the same expressions
        tol = 1e-12 if dtype == torch.float64 else 1e-5
        for a, b in zip(fast[:1] + fast[2:], ref[:1] + ref[2:]):
            assert a.dtype == b.dtype
            assert float(b.abs().max()) > 0
            assert _rel(a, b) < tol
    ratio = fast[1].exp()
    assert bool(((ratio - 1).abs() > 0.2).any()) and bool(((ratio - 1).abs() < 0.2).any())   # both branches


def test_the_kernels_slope_is_autograds_including_ties():
    ratio = torch.tensor([0.5, 0.8, 1.0, 1.1, 1.2, 1.5, 0.8, 1.0, 1.5, 1.2], dtype=torch.float64, requires_grad=True)
    adv = torch.tensor([1.0, 1.0, 1.0, -1.0, 1.0, -2.0, 0.0, -1.0, 1.0, -1.0], dtype=torch.float64)
    (grad,) = torch.autograd.grad(clipped(ratio, adv, 0.2).sum(), ratio)
    slope = torch.tensor([_slope(float(r), float(a), 0.2) for r, a in zip(ratio.detach(), adv)], dtype=torch.float64)
    assert torch.equal(slope, grad)


def test_the_kernels_carrier_width_is_the_specs():
    assert ACT == CARRIER_ACT_DIM


@pytest.mark.parametrize("name", ["sage", "talo_cbf", "sail_cbf", "joint_cbf", "happo"])
def test_talo_gap_matches_the_autograd_chain(name, monkeypatch):
    """g_ind, g_team, W_gap and TALO's HVP on learner minibatches, against the update's start
    (its own ratio) and against a lagged start: the closed-form chain vs the autograd graph."""
    cfg = AlgoConfig(seed=3)
    task = BanditTask(obs_dim=16, seed=3, n_rows=12, human_rate=0.1)
    method = make_method(name, cfg, 16, 48)
    method.proposal.closed_form = False   # the graph with the chain as one Function vs all of it as ops
    batch = collect(method, task, 16, 8, 0.5, np.random.default_rng(3))
    data, _ = method._prepare(batch)
    lagged = data.logp_old + 0.2 * torch.randn(data.logp_old.shape, generator=torch.Generator().manual_seed(1),
                                               dtype=data.logp_old.dtype)
    for logp_start in (None, lagged):
        mb = dataclasses.replace(data, logp_start=logp_start)

        def gap():
            a_st, _, behaviour, start = method.proposal.start_point(mb, 0.3, 5.0)
            return [*method.proposal.gap(a_st, behaviour, with_hvp=True),
                    *method.proposal.gap(a_st, start, with_hvp=False)[:3]]

        fast = gap()
        with monkeypatch.context() as patch:
            patch.setattr(surrogate_chain, "chain_surrogates", reference_surrogates)
            ref = gap()
        assert float(ref[3].abs().max()) > 0          # grad W: the comparison has something to compare
        for a, b in zip(fast, ref):
            a, b = torch.as_tensor(a).double(), torch.as_tensor(b).double()
            if float(b.abs().max()) == 0:                # W_gap at ratio 1 without SAIL's coupling
                assert float(a.abs().max()) == 0
            else:
                assert _rel(a, b) < 1e-5


@pytest.mark.sweep   # two whole updates of six methods, twice: about 15 s
@pytest.mark.parametrize("name", ["sage", "talo_cbf", "sail_cbf", "joint_cbf", "happo", "happo_cbf"])
def test_an_update_steps_where_the_autograd_chain_steps(name, monkeypatch):
    """Two whole updates (every minibatch step, HAPPO's per-carrier surrogates with the M
    factor, the diagnostics and the A/B) from the same state: the same parameters and
    diagnostics to float32 rounding, the learner's closed-form path vs the autograd graph."""
    task = BanditTask(obs_dim=16, seed=4, n_rows=12, human_rate=0.1)

    def run(closed_form):
        method = make_method(name, AlgoConfig(seed=4), 16, 48)
        method.proposal.closed_form = closed_form
        rng = np.random.default_rng(4)
        diags = [method.update(collect(method, task, 16, 8, p, rng), p) for p in (0.2, 0.6)]
        return torch.cat([p.detach().double().reshape(-1) for p in method.actor_params]), diags[-1]

    fast_params, fast = run(closed_form=True)      # the learner's path: TALO's gap in closed form too
    with monkeypatch.context() as patch:
        patch.setattr(surrogate_chain, "chain_surrogates", reference_surrogates)
        ref_params, ref = run(closed_form=False)
    assert _rel(fast_params, ref_params) < 1e-5
    for key in ("policy_loss", "approx_kl", "w_gap_mean", "ab_w_talo"):
        if key in ref:
            assert fast[key] == pytest.approx(ref[key], rel=1e-4, abs=1e-9), key


@pytest.mark.parametrize("name", ["happo", "sail_cbf"])
def test_the_carrier_surrogate_is_happos(name):
    """``ProposalMap.carrier_surrogate`` (the sequential step's L_i with the M factor) against
    the expression it replaced: value, log-ratio and gradient in carrier i's parameters."""
    task = BanditTask(obs_dim=16, seed=5, n_rows=12, human_rate=0.1)
    method = make_method(name, AlgoConfig(seed=5), 16, 48)
    data, _ = method._prepare(collect(method, task, 16, 8, 0.5, np.random.default_rng(5)))
    P, i = method.proposal, 1
    factor = torch.exp(0.3 * torch.randn(data.adv.shape, generator=torch.Generator().manual_seed(2),
                                          dtype=data.adv.dtype))
    mb = dataclasses.replace(data, adv=data.adv * factor)
    a_st = P.tree_actions(mb, 0.4, grad=True)
    step = P.sail_step(mb, a_st, 4.0)
    log_ratio, surr = P.carrier_surrogate(mb, a_st, P.log_std(), 4.0, step, i)
    ref_ratio = P.log_ratio(mb, P.center(mb, a_st, 4.0, step=step), P.log_std())[:, i]
    ref = (P.clipped(ref_ratio.exp(), mb.adv) * mb.active[:, i]).mean()
    assert torch.equal(log_ratio, ref_ratio.detach())
    assert float(surr.detach()) == pytest.approx(float(ref.detach()), rel=1e-12)
    grads = [torch.cat([g.reshape(-1) for g in torch.autograd.grad(s, P.groups[i], retain_graph=True,
                                                                 allow_unused=False)]) for s in (surr, ref)]
    assert float(grads[1].abs().max()) > 0 and _rel(*grads) < 1e-5
    # the sequential step's closed form of the same gradient, from a forward's tapes
    closed_ratio, closed_surr, closed_grad = P.carrier_gradient(mb, a_st.detach(), 4.0, step, i,
                                                                P.policy.taped(mb.obs, 0.4))
    assert torch.equal(closed_ratio, ref_ratio.detach())
    assert float(closed_surr) == pytest.approx(float(ref.detach()), rel=1e-12)
    assert closed_grad.shape == grads[1].shape and _rel(closed_grad, grads[1]) < 1e-5



def test_the_unrolled_sail_gradient_keeps_the_autograd_graph():
    """``sail_grad = "unrolled"`` (a protocol arm) differentiates the unrolled Newton map:
    its surrogates agree with the implicit path's at the converged center, and a whole
    update (both step kinds) runs to finite diagnostics."""
    task = BanditTask(obs_dim=16, seed=6, n_rows=12, human_rate=0.1)
    for name in ("sage", "sail_cbf"):
        methods = {g: make_method(name, AlgoConfig(seed=6, sail_grad=g), 16, 48) for g in ("implicit", "unrolled")}
        batch = collect(methods["implicit"], task, 16, 8, 0.5, np.random.default_rng(6))
        values = {}
        for g, method in methods.items():
            data, _ = method._prepare(batch)
            mb = method.proposal.prepared(data)
            _, _, behaviour, _ = method.proposal.start_point(mb, 0.3, 5.0)
            values[g] = torch.stack([*behaviour.L_ind, behaviour.L_team]).detach()
        assert float(values["implicit"].abs().max()) > 0
        torch.testing.assert_close(values["unrolled"], values["implicit"], rtol=1e-6, atol=1e-9)
        diag = methods["unrolled"].update(batch, 0.5)
        assert all(np.isfinite(v) for k, v in diag.items() if k in ("policy_loss", "w_gap", "approx_kl"))
