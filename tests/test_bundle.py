"""Deployment bundle: standalone (numpy + QP only) and identical to the full deployment stack."""
import json
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np
import pytest

from common.audit.bundle import export_bundle, qp_package_sources
from common.audit.bundle_runtime import Bundle
from common.audit.params import load_params_file, split_carriers
from common.audit.recording import record_episodes
from common.audit.synthetic import random_team_params
from common.env.config import EnvConfig
from common.env.observations import OBS_DIM, OBS_FEATURE_NAMES
from common.policy.tree import team_forward_np
from common.shield.qp import solve_cbf_qp

# A fixed bundle location: re-exporting unchanged QP sources keeps numba's JIT cache in
# <bundle>/sage_qp/__pycache__ valid, so only the first run ever compiles the bundle's kernels.
STABLE_BUNDLE = Path(tempfile.gettempdir()) / f"sage-test-bundle-{os.getuid()}"


@pytest.fixture(scope="module")
def recorded():
    """A short shielded deployment run with a scripted human in slot 1, and its bundle."""
    params = random_team_params(obs_dim=OBS_DIM, depth=4, seed=7)
    rec = record_episodes(params, EnvConfig(scenario="narrow_gate", human_slot=1, max_steps=25), episodes=2, seed=3)
    out = export_bundle(params, STABLE_BUNDLE)
    return params, rec, out


def test_bundle_replays_recorded_deployment_exactly(recorded):
    params, rec, out = recorded
    assert rec.fixed_mask[:, 3:6].all() and (np.abs(rec.a_exec - rec.a_st) > 1e-6).any()  # human + QP both acted
    bundle = Bundle.load(str(out))
    a_exec, traces = bundle.act(rec.obs, (rec.C, rec.c, rec.row_mask), rec.fixed_mask, rec.human_action)
    # the recording is the full stack: team_forward_np -> human block -> solve_cbf_qp
    np.testing.assert_array_equal(traces["leaf"], rec.leaf)
    np.testing.assert_array_equal(traces["nodes"], rec.nodes)
    np.testing.assert_array_equal(traces["sides"], rec.sides)
    np.testing.assert_allclose(traces["a_st"], rec.a_st, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a_exec, rec.a_exec, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(traces["active"], rec.active)
    # and recomputed here from the project's own code, step by step
    a_st, leaves, _, _ = team_forward_np(params, rec.obs[:5])
    a_prop = np.where(rec.fixed_mask[:5], rec.human_action[:5], a_st)
    ref = solve_cbf_qp(a_prop, rec.C[:5], rec.c[:5], rec.row_mask[:5], rec.fixed_mask[:5])
    single, tr = bundle.act(rec.obs[0], (rec.C[0], rec.c[0], rec.row_mask[0]), rec.fixed_mask[0], rec.human_action[0])
    np.testing.assert_allclose(single, ref.a_exec[0], rtol=0, atol=1e-12)
    assert tr["leaf"].tolist() == leaves[0].tolist()


def test_bundle_files_are_human_readable_and_roundtrip(recorded):
    params, _, out = recorded
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith("__")) == \
        ["README.md", "bundle_runtime.py", "sage_qp", "trees.json"]
    doc = json.loads((out / "trees.json").read_text())
    assert doc["feature_names"] == OBS_FEATURE_NAMES
    node = doc["trees"][0]["nodes"][0]
    assert node["predicate"].endswith(f"> {node['b']:.2f}") and "·" in node["predicate"]
    assert "Bundle.load" in (out / "README.md").read_text()
    back = load_params_file(out / "trees.json")  # the audit tools read bundles too
    for a, b in zip(split_carriers(back), split_carriers(params)):
        np.testing.assert_allclose(a.unit_W(), b.unit_W(), atol=1e-15)
        np.testing.assert_array_equal(a.K, b.K)
    # the QP copy is the project's QP with only its package imports made relative
    sources = qp_package_sources()
    assert "from common" not in "".join(sources.values())
    assert (out / "sage_qp" / "__init__.py").read_text() == sources["__init__.py"]


def test_bundle_runs_standalone_without_torch_or_zenoh(recorded, tmp_path):
    _, rec, out = recorded
    moved = out
    np.savez(tmp_path / "step.npz", obs=rec.obs[:3], C=rec.C[:3], c=rec.c[:3], row_mask=rec.row_mask[:3],
             fixed_mask=rec.fixed_mask[:3], human_action=rec.human_action[:3], a_exec=rec.a_exec[:3])
    script = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(moved)!r})
        import numpy as np
        from bundle_runtime import Bundle
        d = np.load({str(tmp_path / 'step.npz')!r})
        a, tr = Bundle.load({str(moved)!r}).act(d["obs"], (d["C"], d["c"], d["row_mask"]), d["fixed_mask"], d["human_action"])
        assert np.abs(a - d["a_exec"]).max() <= 1e-12, np.abs(a - d["a_exec"]).max()
        bad = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "zenoh", "common", "services", "mujoco"))
        print("FORBIDDEN", bad)
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "FORBIDDEN []" in res.stdout


def test_bundle_rejects_bad_input(tmp_path):
    params = random_team_params(obs_dim=4, depth=2)
    out = export_bundle(params, tmp_path / "b", names=list("abcd"))
    bundle = Bundle.load(str(out))
    C, c = np.zeros((2, 9)), np.zeros(2)
    with pytest.raises(ValueError, match="observations must be"):
        bundle.act(np.zeros((3, 5)), (C, c, None))
    with pytest.raises(ValueError, match="NaN"):
        bundle.act(np.full((3, 4), np.nan), (C, c, None))
    with pytest.raises(ValueError, match="human_action is None"):
        bundle.act(np.zeros((3, 4)), (C, c, None), fixed_mask=np.arange(9) < 3)
    (out / "trees.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(ValueError, match="unknown bundle format"):
        Bundle.load(str(out))
