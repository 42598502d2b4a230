"""Adam (Kingma & Ba, 2015), the learner's optimizer, written out.

It computes what ``torch.optim.Adam`` computes with its defaults (no weight
decay, no AMSGrad, not capturable); tests/test_adam.py checks it against
that class bit for bit, and its ``state_dict`` has the same layout, so
checkpoints move between the two. It is written here rather than imported
because constructing any ``torch.optim`` optimizer imports ``torch._dynamo``
(and sympy with it) at every learner start, on the critical path of the
in-process main job, where the actor waits for the first parameters while
the learner builds its optimizers (the figures, before and after, are in
docs/scaling.md, "The learner starts in ..."). The update
runs as one multi-tensor (``torch._foreach_*``) op per line over all the
parameters, which also costs less than ``torch.optim.Adam(fused=True)`` at
these tensor sizes. ``clip_grad_norm``, the clip before every step, is torch's
``clip_grad_norm_`` written out the same way.
"""
from __future__ import annotations

from typing import Iterable

import torch
from torch import Tensor


class Adam:
    """Per parameter p with gradient g, at step t (Kingma & Ba, Algorithm 1,
    in torch's arrangement of the bias corrections):

        m <- beta1 m + (1 - beta1) g
        v <- beta2 v + (1 - beta2) g^2
        p <- p - lr / (1 - beta1^t) * m / (sqrt(v) / sqrt(1 - beta2^t) + eps)

    Parameters without a gradient are skipped, as torch does."""

    def __init__(self, params: Iterable[Tensor], lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8):
        self.params = list(params)
        if not self.params:
            raise ValueError("Adam: no parameters")
        if not (lr > 0 and eps >= 0 and 0 <= betas[0] < 1 and 0 <= betas[1] < 1):
            raise ValueError(f"Adam: need lr > 0, eps >= 0, 0 <= betas < 1 (got {lr}, {eps}, {betas})")
        self.lr, self.betas, self.eps = float(lr), (float(betas[0]), float(betas[1])), float(eps)
        # per-parameter state, created at the parameter's first step (as torch does)
        self.steps: list[int] = [0] * len(self.params)
        self.exp_avg: list[Tensor | None] = [None] * len(self.params)
        self.exp_avg_sq: list[Tensor | None] = [None] * len(self.params)

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        live = [i for i, p in enumerate(self.params) if p.grad is not None]
        if not live:
            return
        beta1, beta2 = self.betas
        for i in live:
            if self.exp_avg[i] is None:
                self.exp_avg[i] = torch.zeros_like(self.params[i], memory_format=torch.preserve_format)
                self.exp_avg_sq[i] = torch.zeros_like(self.params[i], memory_format=torch.preserve_format)
            self.steps[i] += 1
        # one group per step count (all parameters share it unless some skipped a step)
        for t in sorted({self.steps[i] for i in live}):
            idx = [i for i in live if self.steps[i] == t]
            params = [self.params[i] for i in idx]
            grads = [self.params[i].grad for i in idx]
            m = [self.exp_avg[i] for i in idx]
            v = [self.exp_avg_sq[i] for i in idx]
            torch._foreach_lerp_(m, grads, 1 - beta1)
            torch._foreach_mul_(v, beta2)
            torch._foreach_addcmul_(v, grads, grads, 1 - beta2)
            denom = torch._foreach_sqrt(v)
            torch._foreach_div_(denom, (1 - beta2 ** t) ** 0.5)
            torch._foreach_add_(denom, self.eps)
            torch._foreach_addcdiv_(params, m, denom, -self.lr / (1 - beta1 ** t))

    # ------------------------------------------------------------------ checkpoints

    def state_dict(self) -> dict:
        """``torch.optim.Adam``'s layout: ``state`` by parameter index (``step``
        as a float32 scalar tensor, ``exp_avg``, ``exp_avg_sq``) and one param group."""
        state = {i: {"step": torch.tensor(float(self.steps[i])), "exp_avg": self.exp_avg[i].clone(),
                     "exp_avg_sq": self.exp_avg_sq[i].clone()}
                 for i in range(len(self.params)) if self.exp_avg[i] is not None}
        group = {"lr": self.lr, "betas": self.betas, "eps": self.eps, "weight_decay": 0, "amsgrad": False,
                 "maximize": False, "foreach": None, "capturable": False, "differentiable": False,
                 "fused": None, "params": list(range(len(self.params)))}
        return {"state": state, "param_groups": [group]}

    def load_state_dict(self, state: dict) -> None:
        """From ``state_dict`` or ``torch.optim.Adam.state_dict()`` of the same
        parameters; the hyperparameters come with it, as with torch."""
        groups = state.get("param_groups")
        if not isinstance(groups, list) or len(groups) != 1:
            raise ValueError("Adam state: expected one param group")
        group = groups[0]
        if list(group.get("params", [])) != list(range(len(self.params))):
            raise ValueError(f"Adam state is for {len(group.get('params', []))} parameters, "
                             f"this optimizer has {len(self.params)}")
        if group.get("weight_decay", 0) or group.get("amsgrad") or group.get("maximize"):
            raise ValueError("Adam state uses weight decay, AMSGrad or maximize, which this Adam does not")
        steps, exp_avg, exp_avg_sq = [0] * len(self.params), [None] * len(self.params), [None] * len(self.params)
        for key, s in state.get("state", {}).items():
            i, p = int(key), self.params[int(key)]
            if s["exp_avg"].shape != p.shape or s["exp_avg_sq"].shape != p.shape:
                raise ValueError(f"Adam state for parameter {i} has shape {tuple(s['exp_avg'].shape)}, "
                                 f"the parameter {tuple(p.shape)}")
            steps[i] = int(float(s["step"]))
            exp_avg[i] = s["exp_avg"].to(p.dtype).clone()
            exp_avg_sq[i] = s["exp_avg_sq"].to(p.dtype).clone()
        self.lr, self.betas, self.eps = float(group["lr"]), tuple(map(float, group["betas"])), float(group["eps"])
        self.steps, self.exp_avg, self.exp_avg_sq = steps, exp_avg, exp_avg_sq


@torch.no_grad()
def clip_grad_norm(params: Iterable[Tensor], max_norm: float) -> Tensor:
    """``torch.nn.utils.clip_grad_norm_(params, max_norm)`` (2-norm, its multi-tensor path)
    written out: the same kernels in the same order, so the same bits (tests/test_adam.py),
    without the per-call grouping of the gradients by device and dtype, which cost about as
    much as the arithmetic at the learner's sizes (docs/scaling.md, "2026-12-08"). Returns
    the total norm before clipping. Gradients of mixed dtypes or off the CPU go to torch's."""
    params = list(params)
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return torch.tensor(0.0)
    first = grads[0]
    if first.device.type != "cpu" or any(g.dtype != first.dtype or g.device != first.device for g in grads):
        return torch.nn.utils.clip_grad_norm_(params, max_norm)
    total = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads, 2.0)), 2.0)
    torch._foreach_mul_(grads, torch.clamp(float(max_norm) / (total + 1e-6), max=1.0))
    return total
