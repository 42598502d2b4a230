"""Decision-trace recording, its figures (Figs. tree, colortrace) and the `sage trace`/`sage audit` CLI."""
import json

import numpy as np
import pytest

from common.audit.config import AuditConfig
from common.audit.figures import draw_trace, representative_steps
from common.audit.leaf_stats import leaf_audit
from common.audit.recording import Recording, record_episodes
from common.audit.synthetic import random_team_params
from common.env.config import EnvConfig
from common.env.observations import OBS_DIM
from common.policy.tree import team_forward_np
from sage.cli import main


@pytest.fixture(scope="module")
def rec():
    params = random_team_params(obs_dim=OBS_DIM, depth=3, seed=11)
    return record_episodes(params, EnvConfig(scenario="chicane", max_steps=20), episodes=3, seed=5)


def test_recording_is_consistent_with_the_deployment_stack(rec):
    S = rec.n_steps
    lengths = [m["steps"] for m in rec.meta["episode_metrics"]]   # random trees may drop the payload early
    assert S == sum(lengths) and rec.n_episodes == 3 and rec.meta["unfinished"] == 0
    assert all(1 <= n <= 20 for n in lengths)
    for e in range(3):
        assert rec.t[rec.episode == e].tolist() == list(range(lengths[e]))
    a_st, leaves, nodes, sides = team_forward_np(rec.params, rec.obs)
    np.testing.assert_array_equal(leaves, rec.leaf)
    np.testing.assert_array_equal(nodes, rec.nodes)
    np.testing.assert_allclose(a_st, rec.a_st, atol=0)
    # routes end in the recorded leaf: leaf bits are the sides, root first
    depth = rec.sides.shape[2]
    bits = (rec.sides * (2 ** np.arange(depth - 1, -1, -1))).sum(axis=2)
    np.testing.assert_array_equal(bits, rec.leaf)
    # executed actions satisfy the enforced rows (the QP was feasible on these steps)
    slack = np.einsum("smd,sd->sm", rec.C, rec.a_exec) - rec.c
    assert (slack[rec.row_mask] >= -1e-7).all()
    assert (np.abs(rec.a_exec) <= 1 + 1e-12).all()
    assert ((rec.progress >= 0) & (rec.progress <= 1)).all()
    assert rec.payload_pose.shape == (S, 3) and np.isfinite(rec.payload_pose).all()
    assert len(rec.meta["episode_metrics"]) == 3


def test_unshielded_recording_executes_the_clipped_tree_command():
    params = random_team_params(obs_dim=OBS_DIM, depth=2, seed=2)
    r = record_episodes(params, EnvConfig(scenario="narrow_gate", max_steps=5), episodes=1, seed=0, shielded=False)
    np.testing.assert_array_equal(r.a_exec, np.clip(r.a_st, -1, 1))
    assert not r.active.any()


def test_save_load_roundtrip(rec, tmp_path):
    path = rec.save(tmp_path / "r.npz")
    back = Recording.load(path)
    for name in Recording._ARRAYS:
        np.testing.assert_array_equal(getattr(back, name), getattr(rec, name))
    assert back.params.keys() == rec.params.keys()
    assert back.meta["scenario"] == "chicane" and back.meta["feature_names"] == rec.meta["feature_names"]
    with pytest.raises(ValueError, match=".npz"):
        rec.save(tmp_path / "r.msgpack")
    np.savez(tmp_path / "x.npz", leaf=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="not a SAGE recording"):
        Recording.load(tmp_path / "x.npz")


def test_representative_steps_pick_routes_that_part_early(rec):
    s1, s2 = representative_steps(rec, carrier=0)
    l1, l2 = int(rec.leaf[s1, 0]), int(rec.leaf[s2, 0])
    visited = set(rec.leaf[:, 0].tolist())
    if len({l >> 2 for l in visited}) > 1:  # leaves on both sides of the root were visited
        assert (l1 >> 2) != (l2 >> 2)       # depth 3: the top bit is the root decision
    assert l1 != l2 or len(visited) == 1


@pytest.mark.sweep
def test_trace_and_audit_cli(rec, tmp_path, capsys):
    path = rec.save(tmp_path / "r.npz")
    assert main(["trace", str(path), "--out", str(tmp_path / "trace.png"), "--carrier", "2"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (tmp_path / "trace.png").read_bytes()[:4] == b"\x89PNG"
    assert info["leaves"] == [int(rec.leaf[s, 2]) for s in info["steps"]]
    assert main(["audit", str(path), "--out", str(tmp_path / "audit"), "--shuffles", "20"]) == 0
    out = capsys.readouterr().out
    assert "Joint tuple" in out
    saved = json.loads((tmp_path / "audit" / "leaf_audit.json").read_text())
    expect = leaf_audit(rec.leaf, rec.progress, AuditConfig(shuffles=20))
    assert saved["joint"]["purity"] == pytest.approx(expect["joint"]["purity"])
    assert saved["individual_mean"]["nmi"] == pytest.approx(expect["individual_mean"]["nmi"])
    assert (tmp_path / "audit" / "colortrace.png").stat().st_size > 10_000
    # tree view with visit counts from the recording
    np.savez(tmp_path / "p.npz", **rec.params)
    assert main(["tree", "show", str(tmp_path / "p.npz"), "--eval-log", str(path)]) == 0
    text = capsys.readouterr().out
    assert "·vel_x" in text or "·progress" in text or "·lookahead_dx" in text  # named features
    n0 = int((rec.leaf[:, 0] == 0).sum())
    assert f"L0: [" in text and f"visits {n0} (" in text


def test_draw_trace_rejects_bad_carrier(rec, tmp_path):
    with pytest.raises(ValueError, match="carrier 5"):
        draw_trace(rec, str(tmp_path / "t.png"), carrier=5)
