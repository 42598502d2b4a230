"""Actor-side step: propose() composes tree -> SAIL -> proposal, human blocks, modes."""
import subprocess
import sys

import numpy as np
import pytest
import torch

from common.policy.proposal import proposal_log_prob_np
from common.policy.rollout import propose
from common.policy.sail import sail_project_np
from common.policy.tree import team_forward_np
from common.policy.tree_torch import TeamPolicy
from common.safety_rows import SafetyRows

B, N, OBS, M, D = 32, 3, 12, 34, 9


@pytest.fixture(scope="module")
def params():
    torch.manual_seed(0)
    team = TeamPolicy(N, OBS)
    with torch.no_grad():
        for tree in team.trees:
            tree.K.normal_(0.0, 0.4)
    return team.export_params()


def _inputs(seed):
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(B, N, OBS)).astype(np.float32)
    C = rng.normal(size=(B, M, D)) * (rng.random((B, M, 1)) < 0.5)
    c = rng.normal(0.0, 0.5, (B, M)) - 0.5
    row_mask = rng.random((B, M)) < 0.9
    human = rng.uniform(-1, 1, (B, D))
    return obs, C, c, row_mask, human


def test_actor_module_does_not_import_torch():
    code = "import sys, common.policy.rollout; assert 'torch' not in sys.modules, 'torch imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_train_step_composes_tree_sail_and_proposal(params):
    obs, C, c, row_mask, human = _inputs(0)
    no_human = np.zeros(D, bool)
    out = propose(params, obs, SafetyRows(C, c, row_mask, no_human), human, np.random.default_rng(1), "train", kappa=10.0)
    assert set(out) == {"a_st", "a_bar", "a_prop", "logp", "leaf", "nodes", "sides", "a_tree"}
    a_st, leaf, nodes, sides = team_forward_np(params, obs)
    np.testing.assert_array_equal(out["a_st"], a_st)
    np.testing.assert_array_equal(out["leaf"], leaf)
    np.testing.assert_array_equal(out["nodes"], nodes)
    np.testing.assert_array_equal(out["sides"], sides)
    np.testing.assert_allclose(out["a_bar"], sail_project_np(a_st, C, c, row_mask, 10.0), atol=1e-12)
    assert not np.allclose(out["a_bar"], a_st)  # some rows were violated and SAIL moved the center
    log_std = np.concatenate([params[f"carrier_{i}/log_std"] for i in range(N)])
    np.testing.assert_allclose(out["logp"], proposal_log_prob_np(out["a_bar"], log_std, out["a_prop"]), rtol=1e-12)
    assert out["logp"].shape == (B, N) and np.all(np.abs(out["a_prop"]) < 1)
    # the rng alone drives the sampling
    again = propose(params, obs, SafetyRows(C, c, row_mask, no_human), human, np.random.default_rng(1), "train", kappa=10.0)
    np.testing.assert_array_equal(again["a_prop"], out["a_prop"])
    other = propose(params, obs, SafetyRows(C, c, row_mask, no_human), human, np.random.default_rng(2), "train", kappa=10.0)
    assert not np.any(other["a_prop"] == out["a_prop"])


def test_proposal_is_centered_on_sail_center(params):
    obs, C, c, row_mask, human = _inputs(2)
    one = lambda x: np.repeat(x[:1], 4000, 0)  # noqa: E731
    out = propose(params, one(obs), SafetyRows(one(C), one(c), one(row_mask), np.zeros(D, bool)), one(human), np.random.default_rng(0), "train", kappa=5.0)
    mu = np.arctanh(np.clip(out["a_bar"][0], -1 + 1e-3, 1 - 1e-3))
    sigma = np.exp(np.concatenate([params[f"carrier_{i}/log_std"] for i in range(N)]))
    z = (np.arctanh(out["a_prop"]).mean(0) - mu) / (sigma / np.sqrt(4000))
    assert np.all(np.abs(z) < 4.5)


def test_use_sail_false_and_deploy_mode(params):
    obs, C, c, row_mask, human = _inputs(3)
    out = propose(params, obs, SafetyRows(C, c, row_mask, np.zeros(D, bool)), human, np.random.default_rng(0), "train", kappa=10.0,
                  use_sail=False)
    np.testing.assert_array_equal(out["a_bar"], out["a_st"])
    dep = propose(params, obs, SafetyRows(C, c, row_mask, np.zeros(D, bool)), human, np.random.default_rng(0), "deploy", kappa=10.0)
    np.testing.assert_array_equal(dep["a_prop"], dep["a_st"])
    np.testing.assert_array_equal(dep["a_st"], team_forward_np(params, obs)[0])
    assert np.all(dep["logp"] == 0)
    dep2 = propose(params, obs, SafetyRows(C, c, row_mask, np.zeros(D, bool)), human, np.random.default_rng(9), "deploy", kappa=10.0)
    np.testing.assert_array_equal(dep2["a_prop"], dep["a_prop"])  # deterministic


def test_human_block_replaces_actions_and_has_zero_logp(params):
    obs, C, c, row_mask, human = _inputs(4)
    fixed = np.zeros((B, D), bool)
    fixed[: B // 2, 3:6] = True  # carrier 1 is human in the first half of the envs
    out = propose(params, obs, SafetyRows(C, c, row_mask, fixed), human, np.random.default_rng(0), "train", kappa=10.0)
    for key in ("a_st", "a_bar", "a_prop"):
        np.testing.assert_array_equal(out[key][fixed], human[fixed])
    assert np.all(out["logp"][: B // 2, 1] == 0) and np.all(out["logp"][:, [0, 2]] != 0)
    assert np.all(out["logp"][B // 2 :, 1] != 0)
    # robot blocks: SAIL with the human block held fixed
    expected = sail_project_np(np.where(fixed, human, team_forward_np(params, obs)[0]), C, c, row_mask, 10.0,
                               fixed_mask=fixed, fixed_action=human)
    np.testing.assert_allclose(out["a_bar"], expected, atol=1e-12)
    dep = propose(params, obs, SafetyRows(C, c, row_mask, fixed), human, np.random.default_rng(0), "deploy", kappa=10.0)
    np.testing.assert_array_equal(dep["a_prop"][fixed], human[fixed])


def test_bad_inputs(params):
    obs, C, c, row_mask, human = _inputs(5)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="mode"):
        propose(params, obs, SafetyRows(C, c, row_mask, np.zeros(D, bool)), human, rng, "eval", kappa=1.0)
    partial = np.zeros(D, bool)
    partial[3:5] = True
    with pytest.raises(ValueError, match="whole carrier blocks"):
        propose(params, obs, SafetyRows(C, c, row_mask, partial), human, rng, "train", kappa=1.0)
    bad_human = human.copy()
    bad_human[:, 3] = np.nan
    fixed = np.zeros(D, bool)
    fixed[3:6] = True
    with pytest.raises(ValueError, match="human_action"):
        propose(params, obs, SafetyRows(C, c, row_mask, fixed), bad_human, rng, "train", kappa=1.0)
    with pytest.raises(ValueError, match="kappa"):
        propose(params, obs, SafetyRows(C, c, row_mask, np.zeros(D, bool)), human, rng, "train", kappa=-1.0)
