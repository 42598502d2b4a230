"""SAIL: shield-annealed proposal-center map (Sec. III-C, Eq. sail_projection).

    a_bar = argmin_x  1/2 ||x - a_ST||^2 + kappa/2 * sum_j [c_j - C_j x]_+^2

over x in R^d (no box: the proposal distribution handles the box, see
common/proposal.py). Rows are normalized first (`normalize_rows`) so the
penalty does not depend on row units; zero and masked rows are ignored.

Solver: a fixed number of damped Newton steps from x_0 = a_ST, unrolled (and in
torch differentiated through). On the current positive-residual rows A
(r_j = c_j - C_j x > 0) the objective is quadratic, so the Newton system is

    H = I + kappa C_A^T C_A,    grad = (x - a_ST) - kappa C_A^T r_A,
    x <- x - t H^{-1} grad.

Damping (`damping="armijo"`): t is the first of 1, 1/2, ..., 2^-(n_backtrack-1)
that satisfies the Armijo condition f(x + t dx) <= f(x) + c1 t grad.dx, else 0.
Every accepted step therefore lowers f (monotone), and the objective is convex
and C^1, so plain Newton's possible cycling between active sets is excluded.
All candidate step sizes are evaluated at once (vectorized over the batch);
the chosen t is a piecewise-constant selection and is treated as a constant by
autograd. Inside a region with a fixed active set the full Newton step is exact,
so once it is accepted the unrolled map's Jacobian w.r.t. a_ST is
(I + kappa C_J^T C_J)^{-1} (Eq. sail_jacobian). With no violated row the
gradient is exactly 0 and the map is exactly the identity.

Fixed (human) blocks: pass `fixed_mask`/`fixed_action`; the fixed columns are
moved to the right-hand side (`absorb_fixed`), so SAIL only moves the robot
blocks and leaves the human block exactly at its measured value.

torch is imported inside the torch functions only: actor processes use the
numpy twin and never load torch.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    import torch


@dataclass(frozen=True)
class SailConfig:
    n_newton: int = 8          # unrolled damped Newton steps
    damping: str = "armijo"    # "armijo" (monotone backtracking) or "none" (full steps)
    n_backtrack: int = 12      # candidate step sizes 1, 1/2, ..., 2^-(n_backtrack-1)
    armijo_c: float = 1e-4     # sufficient-decrease constant
    row_tol: float = 1e-9      # rows with ||C_j|| <= row_tol count as zero rows


_DEFAULT = SailConfig()
_DAMPINGS = ("armijo", "none")


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


# ----------------------------------------------------------------------------- numpy twin


def _objective_np(x, a, Cn, cn, kappa):
    """f(x) = 1/2||x-a||^2 + kappa/2 sum [cn - Cn x]_+^2 per sample (masked rows of Cn, cn are 0)."""
    r = np.maximum(cn - (Cn @ x[..., None])[..., 0], 0.0)
    return 0.5 * np.sum((x - a) ** 2, -1) + 0.5 * kappa * np.sum(r * r, -1)


def _armijo_np(x, dx, grad, a, Cn, cn, kappa, config):
    """Backtracking step sizes t in {1, 1/2, ...} (first that satisfies Armijo, else 0), per sample."""
    f0 = _objective_np(x, a, Cn, cn, kappa)
    slope = np.sum(grad * dx, -1)
    t = np.ones(len(x))
    pending = np.ones(len(x), dtype=bool)
    for _ in range(config.n_backtrack):
        f = _objective_np(x + t[:, None] * dx, a, Cn, cn, kappa)
        pending &= ~(f <= f0 + config.armijo_c * t * slope)
        if not pending.any():
            return t
        t = np.where(pending, 0.5 * t, t)
    return np.where(pending, 0.0, t)  # no decrease found (already at the minimizer up to rounding)


def sail_project_np(
    a_st,
    C,
    c,
    mask,
    kappa,
    n_newton: int = _DEFAULT.n_newton,
    damping: str = _DEFAULT.damping,
    fixed_mask=None,
    fixed_action=None,
    config: SailConfig = _DEFAULT,
) -> np.ndarray:
    """Eq. (sail_projection) in numpy (float64). a_st [B,d], C [B,M,d], c [B,M], mask [B,M],
    kappa scalar or [B] (>= 0). Returns a_bar [B,d]."""
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
    kappa = np.broadcast_to(np.asarray(kappa, dtype=np.float64), (a.shape[0],))
    if not np.all(np.isfinite(kappa)) or np.any(kappa < 0):
        raise ValueError(f"sail: kappa must be finite and >= 0, got {kappa}")
    if fixed_mask is not None:
        fixed = np.broadcast_to(np.asarray(fixed_mask, dtype=bool), a.shape)
        human = np.broadcast_to(np.asarray(fixed_action, dtype=np.float64), a.shape)
        a = np.where(fixed, human, a)
        C, c = absorb_fixed(C, c, fixed, human)
    Cn, cn, keep = normalize_rows(C, c, mask, config.row_tol)

    eye = np.eye(a.shape[1])
    x = a.copy()
    for _ in range(int(n_newton)):
        r = cn - (Cn @ x[..., None])[..., 0]
        active = (r > 0) & keep
        Ca = Cn * active[..., None]
        grad = (x - a) - kappa[:, None] * (np.where(active, r, 0.0)[:, None, :] @ Cn)[:, 0, :]
        H = eye + kappa[:, None, None] * (Ca.transpose(0, 2, 1) @ Ca)
        dx = -np.linalg.solve(H, grad[..., None])[..., 0]
        if damping == "none":
            x = x + dx
            continue
        x = x + _armijo_np(x, dx, grad, a, Cn, cn, kappa, config)[:, None] * dx
    return x


# ----------------------------------------------------------------------------- torch (differentiable)


def sail_project(
    a_st: "torch.Tensor",
    C: "torch.Tensor",
    c: "torch.Tensor",
    mask: "torch.Tensor",
    kappa,
    n_newton: int = _DEFAULT.n_newton,
    damping: str = _DEFAULT.damping,
    fixed_mask=None,
    fixed_action=None,
    config: SailConfig = _DEFAULT,
) -> "torch.Tensor":
    """Eq. (sail_projection) in torch, unrolled and differentiable w.r.t. a_st (and C, c).

    Same forward as `sail_project_np`; computes in the dtype of a_st (use float64 for
    large kappa). kappa: float or tensor broadcastable to [B].
    """
    import torch

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
    if fixed_mask is not None:
        fixed = torch.as_tensor(fixed_mask, dtype=torch.bool, device=a.device).expand(B, d)
        human = torch.as_tensor(fixed_action, dtype=dtype, device=a.device).expand(B, d)
        a = torch.where(fixed, human, a)
        C, c = absorb_fixed(C, c, fixed, human)
    Cn, cn, keep = normalize_rows(C, c, mask, config.row_tol)

    def objective(x):
        r = torch.relu(cn - torch.einsum("bmd,bd->bm", Cn, x))
        return 0.5 * ((x - a) ** 2).sum(-1) + 0.5 * kappa * (r * r).sum(-1)

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
        if damping == "none":
            x = x + dx
            continue
        with torch.no_grad():  # Armijo backtracking; the step size is a constant for autograd
            f0, slope = objective(x), (grad * dx).sum(-1)
            t = torch.ones(B, dtype=dtype, device=a.device)
            pending = torch.ones(B, dtype=torch.bool, device=a.device)
            for _ in range(config.n_backtrack):
                pending &= ~(objective(x + t[:, None] * dx) <= f0 + config.armijo_c * t * slope)
                if not bool(pending.any()):
                    break
                t = torch.where(pending, 0.5 * t, t)
            t = torch.where(pending, torch.zeros_like(t), t)
        x = x + t[:, None] * dx
    return x
