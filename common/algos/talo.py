"""Team-Averaged Lyapunov policy Optimization (TALO), Sec. III-D of the paper.

Everything here is written for *ascent* directions on surrogates: the actor
update is ``theta <- theta + eta * g_TALO``. Callers that use a minimizing
optimizer set ``param.grad = -g``.

Given per-carrier surrogates ``L_i`` (Eq. ppo_surrogates), the team surrogate
``L_team`` and the parameter groups ``theta_1..theta_N``:

    g_ind  = [grad_{theta_i} L_i]_i                    # Eq. (talo_gap)
    g_team = grad_theta L_team
    W_gap  = 1/2 ||g_ind - g_team||^2
    grad W = d W_gap / d theta        (double backward = Hessian-vector products)
    Delta  = grad W . g_ind + sigma * W_gap
    g_TALO = g_ind - [Delta]_+ / (||grad W||^2 + eps) * grad W   # Eq. (talo_projection)

``grad W`` is obtained by differentiating ``W_gap`` through the gradient
graph (``create_graph=True``); no Hessian is ever formed. Gradients are linear,
so ``d = g_ind - g_team`` is taken directly as the blockwise gradient of
``L_i - L_team`` and only that one graph is kept: the double backward is the
single Hessian-vector product ``grad W = J_d^T d`` (``J_d`` the Jacobian of ``d``),
about half the work of differentiating the g_ind and g_team graphs separately;
``g_team`` is a plain gradient and ``g_ind = d + g_team``.

What "exact" means for hard trees: autograd differentiates the graph it is
given. The leaf controllers (``K``, ``beta``) and ``log_std`` enter the hard
forward smoothly, so their blocks of ``g_ind``/``g_team`` and of ``grad W`` are
the true derivatives (away from routing switches; a central finite difference
agrees, tests/test_algos.py). The split parameters (``W``, ``b``) do not: the
forward routing is hard, and their gradient blocks are the straight-through
surrogate of Eq. (st_gate) (``hard + sigmoid(m/tau) - sigmoid(m/tau).detach()``).
So ``W_gap`` itself contains those surrogate blocks, and the split entries of
``grad W`` come from differentiating the straight-through graph twice: they
are neither the derivative of ``W_gap``'s value as the splits move nor any
other exact quantity, and a central finite difference of ``W_gap`` along the
split parameters does not match them (relative error O(1); on the sage test
minibatch of tests/test_algos.py a random split direction gives -4.5e-6 by
finite difference against -8.6e-3 from autograd). ``grad W`` is exact only in
the smooth directions; in the split directions it is a surrogate, like the ST
gradient itself.

Coupled surrogates through an intermediate (``Through``): with SAIL, every
``L_i`` depends on every carrier's parameters, so block ``i`` of ``d`` needs its
own backward pass, and each one walks the SAIL center and carrier ``i``'s tree.
When the trees meet the surrogates only through their stacked actions ``z =
a_ST`` (carrier ``i``'s block a function of ``theta_i`` alone), the chain rule
gives the same blocks more cheaply: ``grad_{theta_i} L = (dL/dz_i) dz_i/dtheta_i``,
so each ``L_i - L_team`` is differentiated only down to ``z`` (and to the
carrier's direct parameters, ``log_std``), the ``N`` block cotangents are put
side by side, and one vector-Jacobian product of ``z`` takes them through all
trees at once. With ``create_graph`` the cotangents keep their own graphs, so
the HVP is the same derivative of the same quantity (tests/test_talo_fast.py).

Partner detachment: the paper forms ``grad_{theta_i} L_i`` with the partner
nominal branches detached before the SAIL map. Because ``theta_i`` enters
only carrier ``i``'s tree, the *value* of that partial derivative is the same
whether partner branches are detached or not; detaching only stops ``L_i``
from sending gradient into ``theta_j``. Here block ``i`` is always the partial
``autograd.grad(L_i, theta_i)``, so callers may build ``L_i`` on the shared
(undetached) graph, and then ``grad W`` keeps the cross-carrier curvature
through SAIL that a detached graph would drop (with the caveat above for the
split parameters). (tests/test_algos.py checks the detached and shared forms agree.)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from torch import Tensor

ParamGroups = Sequence[Sequence[Tensor]]


def flat_grad(output: Tensor, params: Sequence[Tensor], create_graph: bool = False) -> Tensor:
    """Flat gradient of a scalar w.r.t. ``params``; unused parameters give zeros."""
    params = list(params)
    if not output.requires_grad:
        return torch.cat([torch.zeros_like(p).reshape(-1) for p in params])
    grads = torch.autograd.grad(
        output, params, create_graph=create_graph, retain_graph=True, allow_unused=True
    )
    return torch.cat(
        [(torch.zeros_like(p) if g is None else g).reshape(-1) for g, p in zip(grads, params)]
    )


@dataclass(frozen=True)
class Through:
    """Where carrier ``i``'s parameters meet the surrogates: ``z`` (e.g. the stacked
    tree actions a_ST [B, D]), whose slice ``slices[i]`` of the last axis is a function
    of the parameters ``via[i]`` (a subset of group ``i``) and of nothing else that is
    differentiated; the group's other parameters (``log_std``) enter the surrogates
    directly. The slices must tile ``z``'s last axis in order."""
    z: Tensor
    slices: Sequence[slice]
    via: ParamGroups


def _blockwise_gradient(losses: Sequence[Tensor], groups: ParamGroups, create_graph: bool,
                        through: Through | None) -> Tensor:
    """``[grad_{theta_i} losses[i]]_i`` as one flat vector; see ``Through`` for the route."""
    if through is None:
        return torch.cat([flat_grad(L, g, create_graph) for L, g in zip(losses, groups)])
    z = through.z
    if not z.requires_grad:
        raise ValueError("Through.z must carry the graph from the parameters in 'via'")
    if len(through.slices) != len(groups) or len(through.via) != len(groups):
        raise ValueError("Through needs one slice and one parameter list per group")
    stops = [0] + [sl.stop for sl in through.slices]
    if any(sl.start != a for sl, a in zip(through.slices, stops)) or stops[-1] != z.shape[-1]:
        raise ValueError(f"Through slices must tile z's last axis ({z.shape[-1]}) in order")
    direct = [[p for p in g if all(p is not q for q in via)] for g, via in zip(groups, through.via)]
    found: dict[int, Tensor | None] = {}    # id(parameter) -> its block of the result
    cotangents = []
    for L, sl, params in zip(losses, through.slices, direct):
        grads = torch.autograd.grad(L, [z, *params], create_graph=create_graph, retain_graph=True,
                                    allow_unused=True) if L.requires_grad else (None,) * (1 + len(params))
        cotangents.append(torch.zeros_like(z[..., sl]) if grads[0] is None else grads[0][..., sl])
        found.update(zip(map(id, params), grads[1:]))
    via_all = [p for via in through.via for p in via]
    # one vector-Jacobian product of z: block i's cotangent reaches theta_i only
    found.update(zip(map(id, via_all), torch.autograd.grad(
        z, via_all, grad_outputs=torch.cat(cotangents, dim=-1), create_graph=create_graph,
        retain_graph=True, allow_unused=True)))
    return torch.cat([(torch.zeros_like(p) if found.get(id(p)) is None else found[id(p)]).reshape(-1)
                      for g in groups for p in g])


def individual_gradient(
    losses: Sequence[Tensor], groups: ParamGroups, create_graph: bool = False,
    separable: bool = False,
) -> Tensor:
    """``g_ind = [grad_{theta_i} L_i]`` as one flat vector (Eq. talo_gap).

    ``separable=True`` promises that ``L_i`` depends on ``theta`` only through
    ``theta_i`` (identity proposal center, or partners detached); then one
    backward pass of ``sum_i L_i`` gives every block at once.
    """
    _check_groups(losses, groups)
    if separable:
        return flat_grad(torch.stack(list(losses)).sum(), [p for g in groups for p in g], create_graph)
    return torch.cat([flat_grad(L, g, create_graph) for L, g in zip(losses, groups)])


def _check_groups(losses: Sequence[Tensor], groups: ParamGroups) -> None:
    if len(losses) != len(groups):
        raise ValueError(f"{len(losses)} surrogates for {len(groups)} parameter groups")


def cosine(a: Tensor, b: Tensor, eps: float = 1e-12) -> float:
    """cos(a, b); 0 when either vector is zero."""
    na, nb = a.norm(), b.norm()
    if float(na) <= eps or float(nb) <= eps:
        return 0.0
    return float(a @ b / (na * nb))


def talo_project(
    g_ind: Tensor, grad_w: Tensor, w_gap: Tensor | float, sigma: float, eps: float
) -> tuple[Tensor, float]:
    """Eq. (talo_projection): the regularized closest update to ``g_ind`` meeting
    Eq. (talo_condition) ``grad W . g <= -sigma W``. Returns ``(g_TALO, Delta_gap)``.

    With ``grad W = 0`` (or a correction too large to represent) no step along
    ``grad W`` can meet the condition; ``g_ind`` is then returned unchanged.
    With ``eps > 0`` the condition holds up to the regularizer's slack:
    ``grad W . g_TALO = -sigma W + [Delta]_+ eps / (||grad W||^2 + eps)``, which
    matters only where ``||grad W||^2`` is not large against ``eps``.
    """
    if sigma < 0 or eps < 0:
        raise ValueError(f"TALO needs sigma >= 0 and eps >= 0 (got {sigma}, {eps})")
    g_ind = g_ind.detach()
    grad_w = grad_w.detach()
    w = float(w_gap)
    delta = float(grad_w @ g_ind) + sigma * w
    # ||grad W|| of the vector scaled to max |entry| 1: entries below 1e-154 would
    # square to subnormals, which keep only a few bits (a norm off by percents)
    peak = float(grad_w.abs().max()) if grad_w.numel() else 0.0
    if delta <= 0.0 or peak == 0.0:
        return g_ind.clone(), delta
    scaled = grad_w / peak
    norm = peak * float(scaled.norm())
    # delta / (n^2 + eps) * grad_w, written with the unit vector so that a tiny
    # ||grad W|| does not underflow n^2 to 0 (or a denormal) first
    unit = scaled / float(scaled.norm())
    step = (delta / norm) * (norm * norm / (norm * norm + eps)) if eps > 0 else delta / norm
    out = g_ind - step * unit
    if not bool(torch.isfinite(out).all()):
        return g_ind.clone(), delta
    return out, delta


@dataclass
class TaloResult:
    """Flat vectors over the concatenated parameter groups, plus scalars."""
    g_ind: Tensor
    g_team: Tensor
    grad_w: Tensor
    g_talo: Tensor
    w_gap: float
    delta_gap: float
    cos_ind_team: float

    @property
    def corrected(self) -> bool:
        return self.delta_gap > 0.0


def talo_gap(
    losses: Sequence[Tensor], team_loss: Tensor, groups: ParamGroups,
    separable: bool = False, with_hvp: bool = True, through: Through | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Eq. (talo_gap): returns ``(g_ind, g_team, W_gap, grad_theta W_gap)``.

    ``with_hvp=False`` skips the double backward (diagnostics only) and
    returns ``None`` for the last entry; W_gap is computed the same way either way.
    ``through`` (coupled surrogates only) takes the blocks of ``d`` by the route
    ``Through`` describes: the same values and HVP, one pass through the trees.
    """
    _check_groups(losses, groups)
    params = [p for g in groups for p in g]
    # d = g_ind - g_team, block i = grad_{theta_i} (L_i - L_team); the only graph kept
    if separable:   # block i of grad(sum_j L_j) is grad_{theta_i} L_i
        d = flat_grad(torch.stack(list(losses)).sum() - team_loss, params, create_graph=with_hvp)
    else:
        d = _blockwise_gradient([L - team_loss for L in losses], groups, with_hvp, through)
    g_team = flat_grad(team_loss, params)
    w_gap = 0.5 * d.pow(2).sum()
    # double backward: d/dtheta 1/2||d||^2 = J_d^T d, one Hessian-vector product
    grad_w = flat_grad(w_gap, params) if with_hvp else None
    return (d + g_team).detach(), g_team, w_gap.detach(), grad_w


def talo_direction(
    losses: Sequence[Tensor], team_loss: Tensor, groups: ParamGroups,
    sigma: float, eps: float, separable: bool = False,
) -> TaloResult:
    """Full TALO step direction (Eqs. talo_gap, talo_condition, talo_projection)."""
    g_ind, g_team, w_gap, grad_w = talo_gap(losses, team_loss, groups, separable=separable)
    g_talo, delta = talo_project(g_ind, grad_w, w_gap, sigma, eps)
    return TaloResult(
        g_ind=g_ind, g_team=g_team, grad_w=grad_w, g_talo=g_talo,
        w_gap=float(w_gap), delta_gap=delta, cos_ind_team=cosine(g_ind, g_team),
    )


def unflatten_like(vec: Tensor, params: Sequence[Tensor]) -> list[Tensor]:
    """Split a flat vector into tensors shaped like ``params``."""
    out, start = [], 0
    for p in params:
        n = p.numel()
        out.append(vec[start:start + n].view_as(p))
        start += n
    if start != vec.numel():
        raise ValueError(f"vector of {vec.numel()} entries for {start} parameters")
    return out


def equal_length_ab(w_at: Callable[[Tensor], float], w_before: float, g_talo: Tensor, g_ind: Tensor,
                    length: float) -> tuple[float, float]:
    """The local claim of Eq. (talo_condition) as an A/B on a frozen minibatch: W_gap
    after a step of the same length along g_TALO and along g_ind,
    ``(w_at(length g_TALO/||g_TALO||), w_at(length g_ind/||g_ind||))``.

    ``w_at(displacement)`` evaluates W_gap at the frozen minibatch's parameters plus a
    flat displacement. A zero direction is no step (``w_before``); where the correction
    is off, g_TALO = g_ind and the step is evaluated once."""
    if not length >= 0:
        raise ValueError(f"the A/B step length must be >= 0 (got {length})")

    def after(g: Tensor) -> float:
        n = float(g.norm())
        if n == 0.0 or length == 0.0:
            return float(w_before)
        return float(w_at(g * (length / n)))

    w_ind = after(g_ind)
    w_talo = w_ind if torch.equal(g_talo, g_ind) else after(g_talo)
    return w_talo, w_ind
