"""SAIL: shield-annealed proposal-center map (Sec. III-C, Eq. sail_projection).

    a_bar = argmin_x  1/2 ||x - a_ST||^2 + kappa/2 * sum_j [c_j - C_j x]_+^2

over x in R^d (no box: the proposal distribution handles the box, see
common/policy/proposal.py). Rows are normalized first (`normalize_rows`) so the
penalty does not depend on row units; zero and masked rows are ignored.

Solver: a fixed number of damped Newton steps from x_0 = a_ST, unrolled (and in
torch differentiated through). On the current positive-residual rows A
(r_j = c_j - C_j x > 0) the objective is quadratic, so the Newton system is

    H = I + kappa C_A^T C_A,    grad = (x - a_ST) - kappa C_A^T r_A,
    x <- x - t H^{-1} grad.

Damping (`damping="exact"`): if the full step x + dx keeps the active set, it is
the exact minimizer of f (the gradient of the current quadratic piece vanishes
there) and t = 1. Otherwise t is the exact minimizer of the 1-D convex piecewise
quadratic phi(t) = f(x + t dx), found in closed form from the breakpoints
t_j = r_j / (C_j dx) (vectorized, no Python loop over samples). So f never
increases (monotone), and the step stops just past the first row that would
become violated instead of jumping over it: plain full steps (`damping="none"`)
can oscillate between active sets, and backtracking (t = 1/2^k) jams when the
iterate sits on the kink of a nearly active row. t is treated as a constant by
autograd. Inside a region with a fixed active set the accepted full step is
exact, so the unrolled map's Jacobian w.r.t. a_ST is (I + kappa C_J^T C_J)^{-1}
(Eq. sail_jacobian). With no violated row the gradient is exactly 0 and the map
is exactly the identity.

Step count: each step adds or drops active rows. With the default 20 steps,
random problems with 34 rows (about half violated) reach ||grad f|| < 1e-8 for
kappa <= 100 (tests/test_sail.py) and ~99.9% of them at kappa = 1000; the numpy
solver stops early per sample once a full step was exact (typically 2-6 steps).
If the budget runs out, the result is the (monotonically improved) last iterate,
which is still a valid proposal center, just not the exact minimizer.

Fixed (human) blocks: pass `fixed_mask`/`fixed_action`. The fixed columns are
first moved to the right-hand side (`absorb_fixed`: C_r x_r >= c - C_h a_h), then
the reduced rows are normalized, so the penalty acts on unit rows of the robot
subspace that SAIL actually moves (one active row still scales the robots' normal
component by exactly 1/(1+kappa)); rows that involve only the human become zero
and are ignored. The human block stays exactly at its measured value.

numpy solver: `sail_project_np` runs the Newton loop in a compiled numba kernel
(`common/policy/sail_kernels.py`, one loop over samples, nogil so it runs in the actor
and learner threads side by side); `reference.sail_project` (common/policy/reference.py) is
the same solver as a vectorized numpy loop, the reference the kernel is tested against
(tests/test_sail_kernel.py). torch is imported inside the torch functions only: actor
processes use the numpy solver and never load torch.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from common.policy.sail_kernels import sail_newton, sail_newton_implicit, sail_prepare

if TYPE_CHECKING:  # pragma: no cover
    import torch


@dataclass(frozen=True)
class SailConfig:
    n_newton: int = 20         # unrolled damped Newton steps (numpy solver stops early once exact)
    damping: str = "exact"     # "exact" (full step if exact, else exact line search) or "none" (full steps)
    row_tol: float = 1e-9      # rows with ||C_j|| <= row_tol count as zero rows


_DEFAULT = SailConfig()
_DAMPINGS = ("exact", "none")


# ----------------------------------------------------------------------------- shared helpers


def normalize_rows(C, c, mask, tol: float = _DEFAULT.row_tol):
    """Unit-norm rows: (C_j, c_j) / ||C_j|| for nonzero, unmasked rows; others zeroed and masked.

    Works on numpy arrays or torch tensors (same type out). Returns (Cn, cn, mask).
    """
    if isinstance(C, np.ndarray):
        norm = np.linalg.norm(C, axis=-1)
        keep = np.asarray(mask, dtype=bool) & (norm > tol)
        inv = np.where(keep, 1.0 / np.where(keep, norm, 1.0), 0.0)
        return C * inv[..., None], c * inv, keep
    import torch

    norm = torch.linalg.vector_norm(C, dim=-1)
    keep = mask.to(torch.bool) & (norm > tol)
    safe = torch.where(keep, norm, torch.ones_like(norm))  # no 1/0 in the graph
    inv = keep.to(C.dtype) / safe
    return C * inv[..., None], c * inv, keep


def absorb_fixed(C, c, fixed_mask, fixed_action):
    """Move fixed (human) columns to the right-hand side: C_r x_r >= c - C_h a_h.

    numpy or torch. `fixed_mask` [B,d] or [d] bool, `fixed_action` [B,d]. The fixed
    columns of the returned C are zero, so SAIL's gradient on them is exactly zero.
    """
    if isinstance(C, np.ndarray):
        fixed = np.asarray(fixed_mask, dtype=bool)
        fixed_f = fixed.astype(C.dtype)
        shift = np.einsum("...md,...d->...m", C, fixed_f * np.asarray(fixed_action, dtype=C.dtype))
    else:
        import torch

        fixed_f = fixed_mask.to(C.dtype)
        shift = torch.einsum("...md,...d->...m", C, fixed_f * fixed_action.to(C.dtype))
    free_f = 1.0 - fixed_f
    return C * free_f[..., None, :], c - shift


def _check_shapes(a, C, c, mask):
    if a.ndim != 2:
        raise ValueError(f"sail: a_st must be [B,d], got shape {tuple(a.shape)}")
    B, d = a.shape
    if C.ndim != 3 or C.shape[0] != B or C.shape[2] != d:
        raise ValueError(f"sail: C must be [B,M,d]=[{B},M,{d}], got {tuple(C.shape)}")
    M = C.shape[1]
    if tuple(c.shape) != (B, M):
        raise ValueError(f"sail: c must be [B,M]=[{B},{M}], got {tuple(c.shape)}")
    if tuple(mask.shape) != (B, M):
        raise ValueError(f"sail: mask must be [B,M]=[{B},{M}], got {tuple(mask.shape)}")


def _check_options(n_newton, damping):
    if int(n_newton) != n_newton or n_newton < 0:
        raise ValueError(f"sail: n_newton must be a non-negative int, got {n_newton!r}")
    if damping not in _DAMPINGS:
        raise ValueError(f"sail: damping must be one of {_DAMPINGS}, got {damping!r}")


# ----------------------------------------------------------------------------- numpy (the kernels)


def _kappa_per_sample(kappa, B: int) -> np.ndarray:
    """kappa (scalar or [B]) as [B] float64; finite and >= 0, else a ValueError."""
    kappa = np.broadcast_to(np.asarray(kappa, dtype=np.float64), (B,))
    if not np.all(np.isfinite(kappa)) or np.any(kappa < 0):
        raise ValueError(f"sail: kappa must be finite and >= 0, got {kappa}")
    return kappa


def _prepare_np(a_st, C, c, mask, kappa, n_newton, damping, fixed_mask, fixed_action, config,
                compiled: bool = True):
    """Validation, fixed-block absorption and row normalization shared by the kernel and its
    reference (``reference.sail_project``). Returns (a, Cn, cn, keep, kappa [B], n_newton,
    damping). ``compiled``: the absorption and normalization in one compiled pass
    (``sail_kernels.sail_prepare``), else in numpy (``absorb_fixed``, ``normalize_rows``: the
    references' path, common/policy/reference.py)."""
    n_newton = config.n_newton if n_newton is None else n_newton
    damping = config.damping if damping is None else damping
    a = np.asarray(a_st, dtype=np.float64)
    C = np.asarray(C, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    mask = np.asarray(mask)
    _check_shapes(a, C, c, mask)
    _check_options(n_newton, damping)
    if mask.dtype != bool:
        raise ValueError(f"sail: mask must be bool, got {mask.dtype}")
    for name, arr in (("a_st", a), ("C", C), ("c", c)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"sail: {name} contains NaN/Inf")
    kappa = _kappa_per_sample(kappa, a.shape[0])
    if fixed_mask is not None and fixed_action is None:
        raise ValueError("sail: fixed_mask needs fixed_action (the human's measured action)")
    if compiled:
        fixed = np.zeros(a.shape, bool) if fixed_mask is None else np.asarray(fixed_mask, dtype=bool)
        human = a if fixed_mask is None else np.asarray(fixed_action, dtype=np.float64)
        a, Cn, cn, keep = sail_prepare(*(_kernel_array(v, shape, dt) for v, shape, dt in (
            (a, a.shape, np.float64), (C, C.shape, np.float64), (c, c.shape, np.float64),
            (mask, mask.shape, np.bool_), (fixed, a.shape, np.bool_), (human, a.shape, np.float64))),
            float(config.row_tol))
        return a, Cn, cn, keep, kappa, int(n_newton), damping
    if fixed_mask is not None:  # human block held fixed: SAIL acts on the robot subspace
        fixed = np.broadcast_to(np.asarray(fixed_mask, dtype=bool), a.shape)
        human = np.broadcast_to(np.asarray(fixed_action, dtype=np.float64), a.shape)
        a = np.where(fixed, human, a)
        C, c = absorb_fixed(C, c, fixed, human)
    Cn, cn, keep = normalize_rows(C, c, mask, config.row_tol)
    return a, Cn, cn, keep, kappa, int(n_newton), damping


def _kernel_array(v, shape, dtype):
    """``v`` as the one array type the kernels are compiled for (C-contiguous, aligned,
    writeable, of ``shape`` and ``dtype``): as is when it already is one (the common case,
    checked by flags; np.require would cost more than the kernel), else a copy."""
    if v.dtype == dtype and v.shape == shape and v.flags.c_contiguous and v.flags.aligned and v.flags.writeable:
        return v
    return np.array(np.broadcast_to(v, shape), dtype=dtype, order="C")


def _kernel_args(a, Cn, cn, keep, kappa):
    """One compiled signature: C-contiguous, aligned, writeable (a read-only a_st or the
    broadcast kappa would otherwise be a new type, i.e. a fresh compile at run time)."""
    return [_kernel_array(v, v.shape, dt) for v, dt in ((a, np.float64), (Cn, np.float64), (cn, np.float64),
                                                        (keep, np.bool_), (kappa, np.float64))]


def sail_project_np(
    a_st,
    C,
    c,
    mask,
    kappa,
    n_newton: int | None = None,
    damping: str | None = None,
    fixed_mask=None,
    fixed_action=None,
    config: SailConfig = _DEFAULT,
) -> np.ndarray:
    """Eq. (sail_projection) in numpy (float64). a_st [B,d], C [B,M,d], c [B,M], mask [B,M],
    kappa scalar or [B] (>= 0). n_newton/damping default to `config`'s. Returns a_bar [B,d].

    The Newton loop runs in the compiled kernel `sail_kernels.sail_newton` (nogil);
    `reference.sail_project` is the numpy loop it is tested against."""
    a, Cn, cn, keep, kappa, n_newton, damping = _prepare_np(
        a_st, C, c, mask, kappa, n_newton, damping, fixed_mask, fixed_action, config)
    return sail_newton(*_kernel_args(a, Cn, cn, keep, kappa), n_newton, damping == "exact")


def sail_rows_np(C, c, mask, fixed_mask, fixed_action, config: SailConfig = _DEFAULT):
    """``_prepare_np``'s rows alone, (Cn, cn, keep): they depend on the data (rows and the
    human's block), not on a_ST, so the learner prepares a batch's once for all its solves."""
    human = np.asarray(fixed_action, dtype=np.float64)
    _, Cn, cn, keep, _, _, _ = _prepare_np(human, C, c, mask, 0.0, None, None, fixed_mask, fixed_action, config)
    return Cn, cn, keep


def sail_implicit_step_np(a_st, C, c, mask, kappa, fixed_mask, fixed_action,
                          config: SailConfig = _DEFAULT, rows=None, start=None):
    """The learner's implicit SAIL step at the actors' solution: ``(x_star, H_inv, offset)``
    (see ``sail_center_implicit``). ``x_star`` is ``sail_project_np``'s answer for these
    inputs (the same prepared rows and kernel, so the same bits). ``rows``: ``sail_rows_np``'s
    answer for these C, c, mask and human block, if already prepared. ``start`` [B, d]: a
    warm start for the Newton loop (the actors' solution at the behaviour parameters; human
    blocks start at the human's action); then x* is that answer to rounding wherever the loop
    converges (``sail_kernels.sail_newton_implicit``) and the same bits where it does not."""
    if rows is None:
        a, Cn, cn, keep, kappa, n_newton, damping = _prepare_np(
            a_st, C, c, mask, kappa, None, None, fixed_mask, fixed_action, config)
    else:
        a = np.asarray(a_st, dtype=np.float64)
        if not np.all(np.isfinite(a)):
            raise ValueError("sail: a_st contains NaN/Inf")
        kappa = _kappa_per_sample(kappa, a.shape[0])
        a = np.where(np.asarray(fixed_mask, dtype=bool), np.asarray(fixed_action, dtype=np.float64), a)
        (Cn, cn, keep), n_newton, damping = rows, config.n_newton, config.damping
    x0 = np.empty((0, a.shape[1]))
    if start is not None:
        x0 = np.asarray(start, dtype=np.float64)
        if x0.shape != a.shape or not np.all(np.isfinite(x0)):
            raise ValueError(f"sail: start must be finite and shaped like a_st {a.shape}, got {x0.shape}")
        x0 = np.where(np.asarray(fixed_mask, dtype=bool), a, x0) if fixed_mask is not None else np.array(x0)
    return sail_newton_implicit(*_kernel_args(a, Cn, cn, keep, kappa), n_newton, damping == "exact", x0)


# ----------------------------------------------------------------------------- torch (differentiable)


def _line_search_torch(x, dx, a, Cn, cn, kappa):
    """Torch twin of `reference.line_search` (no autograd)."""
    import torch

    r = cn - torch.einsum("bmd,bd->bm", Cn, x)
    s = torch.einsum("bmd,bd->bm", Cn, dx)
    g0, q = ((x - a) * dx).sum(-1), (dx * dx).sum(-1)

    def dphi(t):
        h = torch.relu(r[:, None, :] - t[..., None] * s[:, None, :])
        return g0[:, None] + t * q[:, None] - kappa[:, None] * (h * s[:, None, :]).sum(-1)

    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    tb = r / torch.where(s != 0, s, torch.ones_like(s))
    valid = (s != 0) & (tb > 0)
    tb = torch.where(valid, tb, zero)
    neg = valid & (dphi(tb) < 0)
    lo = torch.where(neg, tb, zero).amax(-1)
    hi = torch.where(valid & ~neg, tb, torch.full_like(tb, float("inf"))).amin(-1)
    mid = torch.where(torch.isfinite(hi), 0.5 * (lo + hi), lo + 1.0)
    on = (r - mid[:, None] * s) > 0
    slope = q + kappa * torch.where(on, s * s, zero).sum(-1)
    t = lo - dphi(lo[:, None])[:, 0] / torch.where(slope > 0, slope, torch.ones_like(slope))
    return torch.where(slope > 0, torch.minimum(torch.maximum(t, lo), hi), torch.ones_like(t))


def sail_project(
    a_st: "torch.Tensor",
    C: "torch.Tensor",
    c: "torch.Tensor",
    mask: "torch.Tensor",
    kappa,
    n_newton: int | None = None,
    damping: str | None = None,
    fixed_mask=None,
    fixed_action=None,
    config: SailConfig = _DEFAULT,
) -> "torch.Tensor":
    """Eq. (sail_projection) in torch, unrolled and differentiable w.r.t. a_st (and C, c).

    Same forward as `sail_project_np`; computes in the dtype of a_st (use float64 for
    large kappa). kappa: float or tensor broadcastable to [B]. n_newton/damping default
    to `config`'s.
    """
    import torch

    n_newton = config.n_newton if n_newton is None else n_newton
    damping = config.damping if damping is None else damping
    _check_shapes(a_st, C, c, mask)
    _check_options(n_newton, damping)
    if mask.dtype != torch.bool:
        raise ValueError(f"sail: mask must be bool, got {mask.dtype}")
    dtype = a_st.dtype
    C, c = C.to(dtype), c.to(dtype)
    for name, arr in (("a_st", a_st), ("C", C), ("c", c)):
        if not bool(torch.isfinite(arr).all()):
            raise ValueError(f"sail: {name} contains NaN/Inf")
    B, d = a_st.shape
    kappa = torch.as_tensor(kappa, dtype=dtype, device=a_st.device).expand(B)
    if not bool(torch.isfinite(kappa).all()) or bool((kappa < 0).any()):
        raise ValueError(f"sail: kappa must be finite and >= 0, got {kappa}")
    a = a_st
    if fixed_mask is not None:  # human block held fixed: SAIL acts on the robot subspace
        fixed = torch.as_tensor(fixed_mask, dtype=torch.bool, device=a.device).expand(B, d)
        human = torch.as_tensor(fixed_action, dtype=dtype, device=a.device).expand(B, d)
        a = torch.where(fixed, human, a)
        C, c = absorb_fixed(C, c, fixed, human)
    Cn, cn, keep = normalize_rows(C, c, mask, config.row_tol)

    eye = torch.eye(d, dtype=dtype, device=a.device)
    x = a
    for _ in range(int(n_newton)):
        r = cn - torch.einsum("bmd,bd->bm", Cn, x)
        active = ((r > 0) & keep).detach()  # the active set is piecewise constant
        act_f = active.to(dtype)
        Ca = Cn * act_f[..., None]
        grad = (x - a) - kappa[:, None] * torch.einsum("bm,bmd->bd", r * act_f, Cn)
        H = eye + kappa[:, None, None] * torch.einsum("bmd,bme->bde", Ca, Ca)
        dx = -torch.linalg.solve(H, grad[..., None])[..., 0]
        with torch.no_grad():  # step size: a constant for autograd
            exact = (((cn - torch.einsum("bmd,bd->bm", Cn, x + dx) > 0) & keep) == active).all(1)
            t = torch.ones(B, dtype=dtype, device=a.device)
            if damping == "exact" and not bool(exact.all()):
                t = torch.where(exact, t, _line_search_torch(x, dx, a, Cn, cn, kappa))
        x = x + t[:, None] * dx
    return x


@dataclass(frozen=True)
class SailStep:
    """SAIL's implicit step at the actors' solution ``x_star`` [B, d], as float64
    tensors: the center is ``x_star - H_inv (offset - a)`` (``sail_center_implicit``).
    It depends on a_ST only through x*, so one step serves every graph built at
    the same a_ST (the sequential methods' next carrier reuses the refresh's)."""
    x_star: torch.Tensor
    H_inv: torch.Tensor       # [B, d, d]
    offset: torch.Tensor      # [B, d]


def sail_step(a_st: torch.Tensor, C: torch.Tensor, c: torch.Tensor, mask: torch.Tensor, kappa: float,
              fixed: torch.Tensor, human: torch.Tensor, config: SailConfig, rows=None,
              start: torch.Tensor | None = None) -> SailStep:
    """The actors' solve at ``a_st`` and the implicit step there (``sail_implicit_step_np``;
    ``rows``: the prepared rows as tensors, if already prepared; ``start``: a warm start)."""
    import torch

    x_np, H_inv, offset = sail_implicit_step_np(
        a_st.detach().double().cpu().numpy(), C.detach().cpu().numpy(), c.detach().cpu().numpy(),
        mask.cpu().numpy(), kappa, fixed.cpu().numpy(), human.detach().cpu().numpy(), config,
        rows=None if rows is None else tuple(r.cpu().numpy() for r in rows),
        start=None if start is None else start.detach().double().cpu().numpy())
    return SailStep(*(torch.as_tensor(v, dtype=torch.float64, device=a_st.device) for v in (x_np, H_inv, offset)))


def sail_center_implicit(a_st: torch.Tensor, C: torch.Tensor, c: torch.Tensor, mask: torch.Tensor,
                         kappa: float, fixed: torch.Tensor, human: torch.Tensor, config: SailConfig,
                         step: SailStep | None = None) -> torch.Tensor:
    """SAIL center (Eq. sail_projection) with implicit-function gradients.

    Forward: the actors' own numpy solver (common.policy.sail.sail_project_np, same
    config), so the learner's center equals the one the behaviour log-probs
    were computed with. Graph: one Newton step taken from that (constant)
    solution x*,

        x = x* - H^{-1} [(x* - a_ST) - kappa C_J^T r_J(x*)],  H = I + kappa C_J^T C_J,

    whose value is x* (the gradient vanishes there) and whose Jacobian in
    a_ST is (I + kappa C_J^T C_J)^{-1}, Eq. (sail_jacobian) of the ideal
    minimizer. It equals the unrolled map's Jacobian once its last full
    Newton step keeps the active set (see the module docstring). All of the step
    but a_ST is constant (x*, the rows, kappa), so it is affine in a_ST: H^{-1} and the
    offset x* - kappa C_J^T r_J come from a compiled kernel with the solve
    (``sail_step``), and the graph is one batched matrix-vector product,
    whose backward and double backward (TALO's HVP) are products with the same
    constant matrix. Differentiable in a_ST only (the rows are data).
    ``step`` may pass ``sail_step``'s answer already computed at these values.
    """
    import torch

    if step is None:
        step = sail_step(a_st, C, c, mask, kappa, fixed, human, config)
    a = torch.where(fixed, human.double(), a_st.double())
    return step.x_star - (step.H_inv @ (step.offset - a)[..., None])[..., 0]
