"""`sage bench learner`'s report on a tiny batch: the cost per sample and the rate agree,
and every timed update is the first one on its batch."""
import numpy as np
import pytest
import torch

from common.algos.config import AlgoConfig
from common.algos.methods import make_method
from common.algos.synthetic import BanditTask, collect
from sage.bench.learner import bench_learner


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
