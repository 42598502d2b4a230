"""The learner's Adam (common/algos/adam.py) against torch.optim.Adam, the
reference it transcribes: the same parameters after every step, bit for bit
against torch's multi-tensor path and to rounding against its fused kernel,
and checkpoints that move between the two."""
from __future__ import annotations

import io
import subprocess
import sys

import pytest
import torch

from common.algos.adam import Adam, clip_grad_norm


def make_params(seed: int, dtype=torch.float32) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    shapes = [(7, 5), (5,), (3, 4, 2), (1,)]
    return [torch.randn(s, generator=gen, dtype=dtype).requires_grad_() for s in shapes]


def grads_for(step: int, params, seed: int) -> list[torch.Tensor | None]:
    gen = torch.Generator().manual_seed(1000 * seed + step)
    out = [torch.randn(p.shape, generator=gen, dtype=p.dtype) * 10.0 ** (i - 2) for i, p in enumerate(params)]
    if step % 3 == 2:
        out[1] = None   # a parameter that gets no gradient this step is skipped (its step count too)
    return out


def run(opt_for, params, steps: int, seed: int, start: int = 0):
    opt = opt_for(params)
    for t in range(start, start + steps):
        opt.zero_grad()
        for p, g in zip(params, grads_for(t, params, seed)):
            p.grad = None if g is None else g.clone()
        opt.step()
    return opt


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_same_parameters_as_torch_bit_for_bit(dtype, seed):
    ours, ref = make_params(seed, dtype), make_params(seed, dtype)
    run(lambda ps: Adam(ps, lr=3e-3, eps=1e-5), ours, 12, seed)
    run(lambda ps: torch.optim.Adam(ps, lr=3e-3, eps=1e-5, foreach=True), ref, 12, seed)
    for a, b in zip(ours, ref):
        assert torch.equal(a, b)


def test_close_to_torch_fused():
    ours, ref = make_params(5), make_params(5)
    run(lambda ps: Adam(ps, lr=1e-3, eps=1e-5), ours, 20, 5)
    run(lambda ps: torch.optim.Adam(ps, lr=1e-3, eps=1e-5, fused=True), ref, 20, 5)
    for a, b in zip(ours, ref):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)


def test_state_dict_moves_both_ways_through_weights_only_load():
    seed = 3

    def roundtrip(state):
        buf = io.BytesIO()
        torch.save(state, buf)
        buf.seek(0)
        return torch.load(buf, weights_only=True)

    def finish(opt_cls, state, params):
        opt = opt_cls(params)
        opt.load_state_dict(roundtrip(state))
        for t in range(6, 12):
            opt.zero_grad()
            for p, g in zip(params, grads_for(t, params, seed)):
                p.grad = None if g is None else g.clone()
            opt.step()
        return params

    def ours(ps):
        return Adam(ps, lr=2e-3, eps=1e-5)

    def theirs(ps):
        return torch.optim.Adam(ps, lr=2e-3, eps=1e-5, foreach=True)

    straight = make_params(seed)
    run(ours, straight, 12, seed)
    for first, second in ((ours, theirs), (theirs, ours), (ours, ours)):
        params = make_params(seed)
        state = run(first, params, 6, seed).state_dict()
        resumed = finish(second, state, [p.detach().clone().requires_grad_() for p in params])
        for a, b in zip(resumed, straight):
            assert torch.equal(a, b), (first.__name__, second.__name__)


def test_refuses_state_it_cannot_continue():
    params = make_params(0)
    state = run(lambda ps: torch.optim.Adam(ps, lr=1e-3, weight_decay=0.1, foreach=True), params, 2, 0).state_dict()
    with pytest.raises(ValueError, match="weight decay"):
        Adam(params, lr=1e-3).load_state_dict(state)
    fewer = run(lambda ps: Adam(ps, lr=1e-3), params[:2], 2, 0).state_dict()
    with pytest.raises(ValueError, match="parameters"):
        Adam(params, lr=1e-3).load_state_dict(fewer)
    with pytest.raises(ValueError):
        Adam(params, lr=0.0)


def test_learner_never_imports_torch_dynamo():
    """The point of writing Adam out: building and updating a learner does not
    import torch._dynamo (any torch.optim optimizer would, 2-4 s per start)."""
    code = ("import sys, numpy as np\n"
            "from common.algos import AlgoConfig, make_method\n"
            "from common.algos.synthetic import BanditTask, collect\n"
            "m = make_method('sage', AlgoConfig(), 6, 0)\n"
            "b = collect(m, BanditTask(obs_dim=6, seed=0, n_rows=4), 4, 4, 0.5, np.random.default_rng(0))\n"
            "m.update(b, 0.5)\n"
            "print('torch._dynamo' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])   # below, near and above the clip
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_clip_is_torchs_bit_for_bit(scale, dtype):
    """clip_grad_norm against torch.nn.utils.clip_grad_norm_ on the same gradients: the
    same total norm and the same clipped gradients, bit for bit; a parameter without a
    gradient is left alone by both."""
    ours, ref = make_params(3, dtype), make_params(3, dtype)
    for a, b, g in zip(ours, ref, grads_for(2, ours, seed=5)):   # step 2: one gradient is None
        a.grad = None if g is None else g * scale
        b.grad = None if g is None else g.clone() * scale
    total = clip_grad_norm(ours, 0.5)
    expected = torch.nn.utils.clip_grad_norm_(ref, 0.5)
    assert torch.equal(total, expected)
    assert (float(total) > 0.5) == (scale >= 1.0)
    for a, b in zip(ours, ref):
        assert (a.grad is None) == (b.grad is None)
        if a.grad is not None:
            assert torch.equal(a.grad, b.grad)


def test_the_clip_of_mixed_dtypes_is_torchs():
    """Gradients of two dtypes take torch's own function (its grouping decides the bits)."""
    ours = make_params(4, torch.float32)[:2] + make_params(4, torch.float64)[2:]
    ref = [p.detach().clone().requires_grad_() for p in ours]
    for a, b in zip(ours, ref):
        a.grad = torch.full_like(a, 3.0)
        b.grad = torch.full_like(b, 3.0)
    assert torch.equal(clip_grad_norm(ours, 1.0), torch.nn.utils.clip_grad_norm_(ref, 1.0))
    for a, b in zip(ours, ref):
        assert torch.equal(a.grad, b.grad)


def test_no_gradients_clip_nothing():
    params = make_params(5)
    assert float(clip_grad_norm(params, 1.0)) == 0.0
