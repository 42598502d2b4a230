"""Files users load are data, not code (issue 32, defect 6): a bundle's python
is never imported by SAGE and a tampered one is refused; NaN weights are
refused; a recording whose npy header claims 2**40 elements is refused before
anything is allocated; out-of-range leaves are one line and exit 2; `--out`
never writes through a symbolic link."""
from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from common.audit.bundle import export_bundle
from common.audit.bundle_runtime import Bundle
from common.audit.recording import Recording
from common.audit.safe_npz import load_npz
from common.audit.synthetic import random_team_params
from sage.cli import main


@pytest.fixture
def bundle_dir(tmp_path):
    return export_bundle(random_team_params(obs_dim=4, depth=2, seed=1), tmp_path / "b", names=list("abcd"))


MARKER_CODE = "\nimport pathlib; pathlib.Path({path!r}).write_text('imported')\n"


def _rehash(bundle_dir, rel):
    """An attacker who also rewrites trees.json's hash of the file changed."""
    import hashlib

    doc = json.loads((bundle_dir / "trees.json").read_text())
    doc["code_sha256"][rel] = hashlib.sha256((bundle_dir / rel).read_bytes()).hexdigest()
    (bundle_dir / "trees.json").write_text(json.dumps(doc))


def test_sage_never_imports_a_bundles_python(bundle_dir, tmp_path):
    marker = tmp_path / "marker"
    init = bundle_dir / "sage_qp" / "__init__.py"
    init.write_text(init.read_text() + MARKER_CODE.format(path=str(marker)))
    with pytest.raises(ValueError, match="sage_qp/__init__.py differs from the exported file"):
        Bundle.load(str(bundle_dir))                  # the hash no longer matches
    _rehash(bundle_dir, "sage_qp/__init__.py")
    bundle = Bundle.load(str(bundle_dir))             # hashes consistent: loaded, as data only
    assert not marker.exists()
    assert bundle.qp.__name__ == "common.shield.qp"   # the project's own exact QP runs
    (bundle_dir / "sage_qp" / "extra.py").write_text("x = 1\n")
    with pytest.raises(ValueError, match="extra.py"):
        Bundle.load(str(bundle_dir))


def test_nan_or_malformed_tree_weights_are_refused(bundle_dir):
    doc = json.loads((bundle_dir / "trees.json").read_text())
    doc["trees"][1]["leaves"][2]["K"][0][1] = float("nan")
    (bundle_dir / "trees.json").write_text(json.dumps(doc))   # json writes the NaN literal
    with pytest.raises(ValueError, match="carrier 1 leaf gains K holds NaN"):
        Bundle.load(str(bundle_dir))
    doc["trees"][1]["leaves"][2]["K"][0][1] = 0.0
    doc["trees"][0]["nodes"] = doc["trees"][0]["nodes"][:1]
    (bundle_dir / "trees.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="not a complete tree"):
        Bundle.load(str(bundle_dir))
    with pytest.raises(ValueError, match="NaN"):                # nor are they exported
        export_bundle({**random_team_params(obs_dim=4, depth=2), "carrier_0/b": np.array([np.nan] * 3)},
                      bundle_dir.parent / "c", names=list("abcd"))


def _huge_header_npz(path, name="leaf", shape=(2**20, 2**20), like=None):
    """A tiny .npz whose member's npy header claims 2**40 int64 elements (8 TiB);
    ``like``: a recording whose other members it carries (only that one is forged)."""
    header = {"descr": "<i8", "fortran_order": False, "shape": shape}
    import io

    from numpy.lib import format as npy_format

    buf = io.BytesIO()
    npy_format.write_array_header_1_0(buf, header)
    with zipfile.ZipFile(path, "w") as z:
        if like is not None:
            with zipfile.ZipFile(like) as src:
                for info in src.infolist():
                    if info.filename != name + ".npy":
                        z.writestr(info.filename, src.read(info))
        z.writestr(name + ".npy", buf.getvalue() + b"\0" * 64)
    return path


def test_an_npy_header_claiming_terabytes_is_refused_before_allocating(tmp_path):
    p = _huge_header_npz(tmp_path / "huge.npz")
    with pytest.raises(ValueError, match="declares 8796093022208 bytes of data but holds"):
        load_npz(p, max_bytes=2**30)
    ok = tmp_path / "ok.npz"
    np.savez(ok, a=np.arange(1000))
    assert load_npz(ok, max_bytes=2**30)["a"].sum() == 499500
    with pytest.raises(ValueError, match="size budget"):
        load_npz(ok, max_bytes=100)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    from common.audit.recording import record_episodes
    from common.env.config import EnvConfig
    from common.env.observations import OBS_DIM

    rec = record_episodes(random_team_params(obs_dim=OBS_DIM, depth=2, seed=3),
                          EnvConfig(scenario="narrow_gate", max_steps=12), episodes=2, seed=0)
    return rec.save(tmp_path_factory.mktemp("rec") / "rec.npz")


def _one_line_exit_2(argv, capsys):
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 2 and len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


@pytest.mark.parametrize("command", ["trace", "audit"])
def test_trace_and_audit_refuse_hostile_recordings_with_one_line(command, recording, tmp_path, capsys):
    out = ["--out", str(tmp_path / ("t.png" if command == "trace" else "audit"))]
    huge = _huge_header_npz(tmp_path / "huge.npz", like=recording)
    assert "declares 8796093022208 bytes" in _one_line_exit_2([command, str(huge), *out], capsys)
    with np.load(recording) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["leaf"] = arrays["leaf"].astype(np.int64)
    arrays["leaf"][3, 0] = 10**6
    bad = tmp_path / "leaf.npz"
    np.savez(bad, **arrays)
    line = _one_line_exit_2([command, str(bad), *out], capsys)
    assert "leaf ids outside 0..3" in line and str(bad) in line
    with pytest.raises(ValueError, match="leaf ids outside"):
        Recording.load(bad)


def test_out_never_writes_through_a_symlink(recording, tmp_path, capsys):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    link = tmp_path / "t.png"
    link.symlink_to(victim)
    assert "symbolic link" in _one_line_exit_2(["trace", str(recording), "--out", str(link)], capsys)
    audit = tmp_path / "audit"
    audit.mkdir()
    (audit / "leaf_audit.json").symlink_to(victim)
    assert "symbolic link" in _one_line_exit_2(["audit", str(recording), "--out", str(audit)], capsys)
    assert victim.read_text() == "precious"
