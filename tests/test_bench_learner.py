"""`sage bench learner`'s report on a tiny batch: the cost per sample and the rate agree,
and every timed update is the first one on its batch."""
import numpy as np
import pytest
import torch

from common.algos.config import AlgoConfig
from common.algos.methods import make_method
from common.algos.synthetic import BanditTask, collect
from sage.bench.learner import bench_learner, profile_kind, update_profile


def test_bench_learner_reports_the_cost_per_sample():
    out = bench_learner(T=2, K=4, obs_dim=8, rows=4, repeats=1, methods=("happo", "sage"))
    for name in ("happo", "sage"):
        assert out["cpu_us_per_sample"][name] > 0
        assert out["cpu_us_per_sample"][name] * out["samples_per_cpu_s"][name] == pytest.approx(1e6)
    cs = out["critic_step"]   # the same run's A/B of the critic step, on the bench's minibatch
    assert cs["minibatch"] == 8 // 2 and cs["autograd_us"] > 0 and cs["written_us"] > 0
    assert cs["written_over_autograd"] > 0
    # the update's critic floor: its 8 steps' matrix products alone, per sample
    assert cs["gemms_us"] > 0 and cs["written_over_gemms"] > 0
    assert out["critic_gemm_floor_us_per_sample"] == pytest.approx(cs["gemms_us"] * out["epochs"] * 2 / 8)
    m = out["machine"]   # what the figures were measured on
    assert m["cpus_available"] >= 1 and m["cpu_model"] and m["torch_cpu_capability"]
    assert set(m["versions"]) == {"python", "numpy", "torch", "mujoco"}


def test_every_timed_update_starts_where_the_batch_was_collected():
    """The bench's last update reports the W_gap of a fresh method's first update on the
    same batch: with updates chained on one batch (the policy drifting from the one that
    collected it) the third would report another."""
    out = bench_learner(T=2, K=4, obs_dim=8, rows=4, repeats=3, methods=("happo", "sage"), seed=3)
    torch.set_num_threads(1)
    for name in ("happo", "sage"):
        method = make_method(name, AlgoConfig(seed=3), 8, 24)
        task = BanditTask(obs_dim=8, seed=3, n_rows=4, human_rate=0.05)
        batch = collect(method, task, 2, 4, 0.5, np.random.default_rng(3))
        first = method.update(batch, 0.5)["w_gap"]
        # to rounding (a BLAS may round differently with the buffers' alignment); a chained
        # update's differs by 9-48% here
        assert out["w_gap"][name] == pytest.approx(first, rel=1e-9)
        assert method.update(batch, 0.5)["w_gap"] != pytest.approx(first, rel=1e-3)


def test_profile_kinds():
    tree = "/x/common/policy/tree_grad_kernels.py"
    assert profile_kind(tree, "tree_st_hvp") == "tree kernels"
    assert profile_kind("/x/common/policy/sail_kernels.py", "sail_newton_implicit") == "SAIL kernels"
    assert profile_kind("~", "<method 'mm' of 'torch._C.TensorBase' objects>") == "matrix products"
    assert profile_kind("~", "<built-in method torch.addmm>") == "matrix products"
    assert profile_kind("~", "<built-in method torch._ops.aten.tanh_backward>") == "critic tanh"
    assert profile_kind("/x/common/algos/critic.py", "_tanh_") == "critic tanh"
    assert profile_kind("/x/common/algos/critic.py", "value_step") == "Python"
    assert profile_kind("~", "<method 'index_select' of 'torch._C.TensorBase' objects>") == "gather"
    assert profile_kind("~", "<built-in method torch.cat>") == "other torch and numpy calls"
    # a Python function named like a C one is Python; a C one named like a kernel file's is not a kernel
    assert profile_kind("/x/common/algos/joint.py", "mm") == "Python"
    assert profile_kind("~", "tree_st_hvp") == "other torch and numpy calls"


def test_update_profile_splits_the_own_time():
    stats = {("/x/common/policy/tree_grad_kernels.py", 1, "tree_st_hvp"): (2, 2, 0.3, 0.3, {}),
             ("~", 0, "<built-in method torch.addmm>"): (5, 5, 0.2, 0.2, {}),
             ("~", 0, "<method 'reduce' of 'numpy.ufunc' objects>"): (7, 7, 0.1, 0.1, {}),
             ("/x/common/algos/joint.py", 23, "joint_step"): (1, 1, 0.4, 1.0, {})}
    out = update_profile(stats, samples=100)
    assert out["us_per_sample"] == pytest.approx(1e6 * 1.0 / 100)
    assert out["share"] == pytest.approx({"Python": 0.4, "tree kernels": 0.3, "matrix products": 0.2,
                                          "other torch and numpy calls": 0.1})
    assert list(out["share"]) == ["Python", "tree kernels", "matrix products", "other torch and numpy calls"]
    assert out["torch_calls"] == 5


def test_bench_learner_profiles_an_update_on_request():
    out = bench_learner(T=2, K=4, obs_dim=8, rows=4, repeats=1, methods=("happo", "sage"), profile=True)
    for name in ("happo", "sage"):
        prof = out["profile"][name]
        assert sum(prof["share"].values()) == pytest.approx(1.0)
        assert prof["us_per_sample"] > 0 and prof["torch_calls"] > 0
        assert prof["share"]["tree kernels"] > 0 and prof["share"]["matrix products"] > 0
    assert out["profile"]["sage"]["share"]["SAIL kernels"] > 0
    assert "SAIL kernels" not in out["profile"]["happo"]["share"]
    assert "profile" not in bench_learner(T=2, K=4, obs_dim=8, rows=4, repeats=1, methods=("happo",))
