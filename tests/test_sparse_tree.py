"""Sparse oblique splits (issue: trees a person can read): a k-sparse tree
keeps at most k features per split after every update of every method, its
numpy twin and deployment bundle act as the torch tree does, and its
predicates print in full with physical units."""
import re

import numpy as np
import pytest
import torch

from common.algos.config import AlgoConfig
from common.algos.methods import make_method
from common.algos.synthetic import BanditTask, collect
from common.audit.bundle import export_bundle
from common.audit.bundle_runtime import Bundle
from common.audit.params import feature_names, feature_units_of, split_carriers
from common.audit.tree_view import describe_tree
from common.env.observations import OBS_DIM
from common.policy.tree import TreeConfig, team_forward_np
from common.policy.tree_torch import (
    TeamPolicy,
    policy_params_from_checkpoint,
    top_k_mask,
)
from services.config import TrainConfig


def nonzeros_per_row(x: torch.Tensor) -> torch.Tensor:
    return (x != 0).sum(-1)


def test_top_k_mask_keeps_the_largest_magnitudes():
    x = torch.tensor([[0.1, -3.0, 2.0, 0.5], [1.0, 1.5, -0.2, 0.0]])
    np.testing.assert_array_equal(top_k_mask(x, 2).numpy(), [[0, 1, 1, 0], [1, 1, 0, 0]])
    assert (top_k_mask(x, 0) == 1).all() and (top_k_mask(x, 9) == 1).all()


@pytest.mark.parametrize("method", ["happo", "sage", "talo_cbf"])
@pytest.mark.parametrize("k", [1, 3])
def test_k_sparse_tree_stays_k_sparse_after_every_update(method, k):
    cfg = AlgoConfig(split_k=k, leaf_k=k + 1, epochs=2, minibatches=2, seed=1)
    m = make_method(method, cfg, OBS_DIM, 3 * OBS_DIM)
    task = BanditTask(obs_dim=OBS_DIM, seed=0, n_rows=8, human_rate=0.0)
    rng = np.random.default_rng(0)
    dense0 = [t.W.detach().clone() for t in m.policy.trees]
    for update in range(4):
        params = m.policy_params()   # what actors receive after every update
        for i in range(3):
            assert ((params[f"carrier_{i}/W"] != 0).sum(1) <= k).all(), f"update {update}"
            assert ((params[f"carrier_{i}/W"] != 0).sum(1) >= 1).all()   # a split always keeps a feature
            assert ((params[f"carrier_{i}/K"] != 0).sum(-1) <= k + 1).all()
        for tree in m.policy.trees:   # the learner's forward is the same sparse tree
            assert (nonzeros_per_row(tree.split_W()) <= k).all()
        m.update(collect(m, task, 16, 8, update / 4, rng), update / 4)
    # the dropped features still get gradient (straight-through), so the choice can change
    moved = [((t.W.detach() - w0).abs() * (1 - top_k_mask(w0, k))).max() for t, w0 in zip(m.policy.trees, dense0)]
    assert max(moved) > 0


def test_numpy_twin_and_bundle_agree_with_the_sparse_torch_tree(tmp_path):
    torch.manual_seed(0)
    team = TeamPolicy(3, OBS_DIM, config=TreeConfig(depth=3, split_k=2, leaf_k=3))
    obs = np.random.default_rng(2).normal(size=(64, 3, OBS_DIM)).astype(np.float32)
    with torch.no_grad():
        ref = team(torch.from_numpy(obs))
    params = team.export_params()
    a_np, leaf_np, nodes_np, sides_np = team_forward_np(params, obs)
    np.testing.assert_array_equal(leaf_np, ref.leaf.numpy())
    np.testing.assert_array_equal(nodes_np, ref.nodes.numpy())
    np.testing.assert_allclose(a_np, ref.action.numpy(), atol=1e-5)
    bundle = Bundle.load(str(export_bundle(params, tmp_path / "bundle")))
    for i, tree in enumerate(bundle.trees):
        action, leaf, nodes, _ = tree.forward(obs[:, i].astype(np.float64))
        np.testing.assert_array_equal(leaf, ref.leaf[:, i].numpy())
        np.testing.assert_allclose(action, a_np[:, 3 * i:3 * i + 3], atol=1e-9)


def test_a_checkpoint_of_a_sparse_run_exports_the_sparse_trees():
    # the checkpoint holds the dense straight-through weights; sage eval, export-bundle
    # and tree show must still get the k-sparse trees the run's actors ran
    cfg = TrainConfig(run_id="t", algo={"split_k": 2, "leaf_k": 3})
    m = make_method("sage", cfg.algo, OBS_DIM, 3 * OBS_DIM)
    ckpt = {"method": m.state_dict(), "config": cfg.to_json()}
    live, restored = m.policy_params(), policy_params_from_checkpoint(ckpt)
    assert live.keys() == restored.keys()
    for key in live:
        np.testing.assert_array_equal(restored[key], live[key])
    assert ((restored["carrier_0/W"] != 0).sum(1) <= 2).all()


def test_sparse_predicates_print_every_term_with_units():
    torch.manual_seed(3)
    params = TeamPolicy(3, OBS_DIM, config=TreeConfig(depth=2, split_k=1)).export_params()
    names = feature_names(OBS_DIM)
    units = feature_units_of(names)
    crisp = describe_tree(split_carriers(params)[0], names, units=units)
    for node in crisp["nodes"]:
        # a one-feature split is a threshold on the quantity itself
        assert re.fullmatch(r"\w+ [<>] -?\d+\.\d\d( (m|rad|m/s|rad/s))?", node["predicate"]), node["predicate"]
        assert node["n_features"] == 1
    params = TeamPolicy(3, OBS_DIM, config=TreeConfig(depth=2, split_k=3)).export_params()
    tree = split_carriers(params)[0]
    for node, w in zip(describe_tree(tree, names, units=units)["nodes"], tree.unit_W()):
        used = [names[j] for j in np.flatnonzero(w)]
        assert len(used) == 3 and all(n in node["predicate"] for n in used) and "more" not in node["predicate"]
        assert any(f"{n}[" in node["predicate"] for n in used)   # unit-carrying terms
    # the units are the features' real scales: goal_dx is (payload -> goal x) / 5 m
    assert units["goal_dx"] == (5.0, "m") and units["vel_yaw"][1] == "rad/s"


def test_a_split_in_one_unit_reads_as_a_unit_normal_and_a_distance():
    # w.o > b on goal_dx = q1 / 5 m and wall_dist_front = q2 / 2 m is
    # (w1/5) q1 + (w2/2) q2 > b; rescaled to a unit normal in metres the threshold is in m
    names = feature_names(OBS_DIM)
    units = feature_units_of(names)
    params = TeamPolicy(3, OBS_DIM, config=TreeConfig(depth=1, split_k=2, leaf_k=1)).export_params()
    W = np.zeros((1, OBS_DIM), np.float32)
    W[0, names.index("goal_dx")], W[0, names.index("wall_dist_front")] = 0.6, -0.8
    params["carrier_0/W"], params["carrier_0/b"] = W, np.array([0.1], np.float32)
    desc = describe_tree(split_carriers(params)[0], names, units=units)
    coef = np.array([0.6 / 5.0, -0.8 / 2.0])
    n = np.linalg.norm(coef)
    assert desc["nodes"][0]["predicate"] == (f"−{-coef[1] / n:.2f}·wall_dist_front[m] + {coef[0] / n:.2f}·goal_dx[m]"
                                             f" > {0.1 / n:.2f} m")   # largest |term| first
    for gain in desc["leaves"][0]["gains"].values():   # a 1-sparse leaf row: one unit-carrying term, all shown
        assert "more" not in gain and gain.count("·") <= 1


@pytest.mark.parametrize("bad", [{"split_k": -1}, {"leaf_k": -2}])
def test_bad_sparsity_is_refused(bad):
    with pytest.raises(ValueError, match="split_k|leaf_k"):
        AlgoConfig(**bad)
    with pytest.raises(ValueError, match="split_k|leaf_k"):
        TrainConfig(run_id="t", algo=bad).validate()
