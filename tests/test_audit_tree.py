"""Tree views: predicates with named features, leaf commands, visit counts, file formats."""
import json

import numpy as np
import pytest

from common.audit.config import AuditConfig
from common.audit.params import BadPolicyParams, load_params_file, save_params_json, split_carriers
from common.audit.synthetic import random_team_params
from common.audit.tree_view import describe_tree, format_linear, leaf_path, tree_dot, tree_png, tree_text
from sage.cli import main


def test_format_linear_orders_by_magnitude_and_folds_the_rest():
    names = ["a", "b", "c", "d"]
    assert format_linear(np.array([0.1, -0.41, 0.82, 0.05]), names, 2) == "0.82·c − 0.41·b + (2 more, |w|≤0.10)"
    assert format_linear(np.array([-0.6, 0.8]), ["x", "y"], 3) == "0.80·y − 0.60·x"
    assert format_linear(np.array([-0.6, 0.3]), ["x", "y"], 1) == "−0.60·x + (1 more, |w|≤0.30)"


def _one_node_tree():
    # one split on 2*x0 > 0.5 (unit w = [1, 0]); leaf 0 = "no", leaf 1 = "yes"
    return {"carrier_0/W": np.array([[2.0, 0.0]]), "carrier_0/b": np.array([0.5]),
            "carrier_0/K": np.zeros((2, 3, 2)), "carrier_0/beta": np.array([[0.0, 0.0, 0.0], [1.0, -1.0, 0.5]]),
            "carrier_0/c_a": np.array([0.0, 0.0, 0.1]), "carrier_0/s_a": np.array([1.0, 0.5, 0.2])}


def test_describe_hand_built_tree():
    (tree,) = split_carriers(_one_node_tree())
    desc = describe_tree(tree, ["lookahead_dx", "wall_dist"], AuditConfig(top_terms=3), visits=np.array([3, 1]))
    assert desc["nodes"][0]["predicate"] == "1.00·lookahead_dx > 0.50"   # a zero weight is no term
    assert desc["nodes"][0]["left"] == 1 and desc["nodes"][0]["right"] == 2
    right = desc["leaves"][1]
    expect = [np.tanh(1.0), 0.5 * np.tanh(-1.0), 0.1 + 0.2 * np.tanh(0.5)]
    assert right["bias_command"] == pytest.approx(expect, abs=1e-4)
    assert right["bounds"] == [[-1.0, 1.0], [-0.5, 0.5], [pytest.approx(-0.1), pytest.approx(0.3)]]
    assert right["path"] == [{"node": 0, "side": "right"}]
    assert right["visits"] == 1 and right["visit_share"] == 0.25


def test_leaf_paths_follow_heap_order():
    (tree, *_) = split_carriers(random_team_params(depth=4))
    for leaf in range(tree.n_leaves):
        node = 0
        for k, right in leaf_path(tree, leaf):
            assert k == node
            node = 2 * node + 1 + int(right)
        assert node == tree.n_internal + leaf
    # the leaf index bits are the sides, most significant first
    assert [r for _, r in leaf_path(tree, 0b1011)] == [True, False, True, True]


def test_text_json_dot_cover_every_node():
    params = random_team_params(obs_dim=5, depth=3)
    (tree, *_) = split_carriers(params)
    names = [f"f{j}" for j in range(5)]
    desc = describe_tree(tree, names, visits=np.arange(8))
    text = tree_text(desc)
    for k in range(7):
        assert f"N{k}: " in text
    for leaf in range(8):
        assert f"L{leaf}: [" in text
    assert "visits 7" in text
    back = json.loads(json.dumps(desc))
    assert np.allclose(np.array([n["w"] for n in back["nodes"]]), tree.unit_W())
    dot = tree_dot(desc)
    assert dot.count("->") == 14 and dot.strip().endswith("}")


def test_png_is_written(tmp_path):
    (tree, *_) = split_carriers(random_team_params(depth=4, obs_dim=9))
    path = tmp_path / "t.png"
    tree_png(describe_tree(tree, [f"feature_{j}" for j in range(9)], visits=np.ones(16, int)), str(path))
    assert path.stat().st_size > 20_000
    assert path.read_bytes()[:4] == b"\x89PNG"


def test_bad_params_are_rejected(tmp_path):
    params = random_team_params()
    del params["carrier_1/beta"]
    with pytest.raises(BadPolicyParams, match="carrier_1 lacks"):
        split_carriers(params)
    params = random_team_params()
    params["carrier_0/W"][0, 0] = np.nan
    with pytest.raises(BadPolicyParams, match="NaN"):
        split_carriers(params)
    params = random_team_params()
    params["carrier_2/b"] = np.zeros(3)
    with pytest.raises(BadPolicyParams, match="b shape"):
        split_carriers(params)
    with pytest.raises(FileNotFoundError):
        load_params_file(tmp_path / "nope.npz")


def test_cli_tree_from_npz_json_and_checkpoint(tmp_path, capsys):
    import torch

    params = random_team_params(obs_dim=4, depth=2, seed=5)
    np.savez(tmp_path / "p.npz", **params)
    save_params_json(params, tmp_path / "p.json")
    # a checkpoint: the flat params (as tensors) nested in a method-state dict
    torch.save({"version": 3, "policy_params": {k: torch.as_tensor(v) for k, v in params.items()}},
               tmp_path / "ckpt_00000003.pt")
    leaf = np.array([[0, 1, 2], [3, 1, 2], [3, 0, 0]])
    np.savez(tmp_path / "log.npz", leaf=leaf)
    outputs = []
    for src in ("p.npz", "p.json", "ckpt_00000003.pt"):
        assert main(["tree", "show", str(tmp_path / src), "--carrier", "1", "--eval-log", str(tmp_path / "log.npz")]) == 0
        outputs.append(capsys.readouterr().out)
    assert outputs[0].split("\n", 1)[1] == outputs[1].split("\n", 1)[1] == outputs[2].split("\n", 1)[1]
    assert "visits 2 (66.7%)" in outputs[0]  # carrier 1 visited leaf 1 twice out of three
    assert main(["tree", "export", str(tmp_path / "p.npz"), "--format", "dot", "--out", str(tmp_path / "t.dot")]) == 0
    assert (tmp_path / "t.dot").read_text().startswith("digraph")
    with pytest.raises(SystemExit):
        main(["tree", "show", str(tmp_path / "p.npz"), "--carrier", "3"])
