"""The compiled team forward (common/policy/tree_kernels.py) against its numpy
reference (common/policy/reference.py team_forward): same routes, same leaf actions to rounding."""
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from common.policy.tree import (
    InvalidParams,
    TreeConfig,
    ValidatedParams,
    team_forward_np,
)
from common.policy import reference
from common.policy.tree_torch import TeamPolicy


def _params(depth, obs_dim, seed, split_k=0, n_agents=3):
    torch.manual_seed(seed)
    team = TeamPolicy(n_agents, obs_dim, config=TreeConfig(depth=depth, split_k=split_k, b_init_scale=0.5))
    with torch.no_grad():
        for tree in team.trees:
            tree.beta.normal_()
    return team.export_params()


def _agree(params, obs):
    a, leaf, nodes, sides = team_forward_np(params, obs)
    ra, rleaf, rnodes, rsides = reference.team_forward(params, obs)
    np.testing.assert_array_equal(leaf, rleaf)
    np.testing.assert_array_equal(nodes, rnodes)
    np.testing.assert_array_equal(sides, rsides)
    np.testing.assert_allclose(a, ra, rtol=0, atol=1e-12)
    assert a.dtype == np.float64 and leaf.dtype == rleaf.dtype and sides.dtype == bool


@pytest.mark.parametrize("depth,split_k", [(1, 0), (2, 1), (4, 0), (4, 1), (5, 3)])
def test_kernel_equals_reference_on_random_trees(depth, split_k):
    rng = np.random.default_rng(depth)
    for seed in range(4):
        params = _params(depth, 11, seed, split_k)
        obs = rng.normal(scale=2.0, size=(64, 3, 11)).astype(np.float32)
        _agree(params, obs)
        _agree(ValidatedParams(params), obs)       # the actor's path: arrays stacked once


@settings(max_examples=150, deadline=None)
@given(obs=arrays(np.float64, (5, 3, 6), elements=st.floats(-50, 50, allow_nan=False, width=32)),
       seed=st.integers(0, 3))
@pytest.mark.sweep
def test_kernel_equals_reference_on_drawn_observations(obs, seed):
    _agree(_params(3, 6, seed), obs)


def test_every_leaf_reached_and_edge_shapes():
    params = _params(3, 4, 0)
    obs = np.random.default_rng(1).normal(scale=3.0, size=(4000, 3, 4))
    _agree(params, obs)
    assert len(np.unique(team_forward_np(params, obs)[1][:, 0])) == 8
    out = team_forward_np(params, np.zeros((0, 3, 4)))
    assert out[0].shape == (0, 9) and out[2].shape == (0, 3, 3)
    _agree(_params(2, 4, 0, n_agents=1), obs[:, :1])
    with pytest.raises(ValueError):
        team_forward_np(params, np.zeros((2, 3, 5)))
    with pytest.raises(InvalidParams):
        team_forward_np({"format_version": np.float32(1)}, obs)
