"""The campaign protocol (docs/protocol/table1.toml) and suite resumption by config fingerprint."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from common.env.scenarios import FAMILIES
from sage.cli import main
from sage.protocol import load_protocol
from sage.suite import SuiteConfig, check_resume, plan, run_config

ROOT = Path(__file__).resolve().parents[1]
TABLE1 = ROOT / "docs" / "protocol" / "table1.toml"
PAPER_ARMS = {"happo", "happo_cbf", "talo_cbf", "sail_cbf", "sage", "joint_cbf"}


def test_table1_pins_the_papers_settings_on_every_paper_arm(tmp_path):
    proto = load_protocol(TABLE1, out_dir=str(tmp_path))
    arms = {a.name: a for a in proto.suite.arm_list()}
    assert PAPER_ARMS <= set(arms) and set(proto.extension_arms) == set(arms) - PAPER_ARMS
    assert proto.suite.eval_episodes >= 100 and proto.suite.eval_checkpoints == 3
    assert len(proto.suite.scenarios) == 9 and len(proto.suite.seeds) >= 5
    specs = plan(proto.suite)
    for spec in specs:
        tc = run_config(proto.suite, spec, tmp_path / spec.name)
        assert tc.eval_checkpoints == 3 and tc.checkpoint_keep >= 3
        if (spec.arm or spec.method) in PAPER_ARMS:
            assert (tc.algo.split_k, tc.algo.talo_step, tc.algo.sail_grad, tc.max_lag) == (0, "direct", "unrolled", 0)
            assert tc.method == spec.method
    # each extension arm differs from SAGE+CBF's run in its one named setting only
    sage = run_config(proto.suite, next(s for s in specs if s.method == "sage" and not s.arm
                                         and s.scenario == "maze" and s.seed == 0), tmp_path / "a")
    sparse = run_config(proto.suite, next(s for s in specs if s.arm == "sage_sparse" and s.scenario == "maze"
                                          and s.seed == 0), tmp_path / "b")
    assert sparse.algo.split_k == 1 and sparse.algo.talo_step == "direct"
    a, b = json.loads(sage.to_json()), json.loads(sparse.to_json())
    for d in (a, b):
        d.pop("run_id"), d.pop("run_dir"), d["algo"].pop("split_k")
    assert a == b
    # extension arms run on the three CCN scenarios only
    assert {s.scenario for s in specs if s.arm == "sage_sparse"} == set(FAMILIES["CCN"])


def test_dry_run_lists_every_run_and_runs_nothing(tmp_path, capsys):
    out = tmp_path / "t1"
    assert main(["suite", "--protocol", str(TABLE1), "--dry-run", "--out", str(out)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    proto = load_protocol(TABLE1)
    assert len(lines) == len(plan(proto.suite)) + 1 and "fingerprint" in lines[0]
    assert not out.exists()


def test_protocol_refuses_experiment_flags_and_bad_files(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["suite", "--protocol", str(TABLE1), "--dry-run", "--seeds", "1"])
    assert exit_.value.code == 2 and "drop --seeds" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    text = TABLE1.read_text()
    for broken, needle in ((text.replace('"algo.split_k" = 0', '"algo.split_kk" = 0', 1), "split_kk"),
                           (text.replace("eval_checkpoints = 3", "eval_checkpointz = 3"), "eval_checkpointz"),
                           (text.replace('method = "happo_cbf"', 'method = "nope"'), "nope"),
                           (text + "\n[arms.x]\nmethod = \"sage\"\nsettings = { \"algo.epochs\" = 0 }\n", "epochs"),
                           ("not = [toml", "TOML")):
        bad.write_text(broken)
        with pytest.raises(SystemExit) as exit_:
            main(["suite", "--protocol", str(bad), "--dry-run"])
        assert exit_.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err


def _fake_result(cfg: SuiteConfig, spec, fingerprint: str) -> None:
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{spec.name}.json").write_text(json.dumps({"method": spec.method, "fingerprint": fingerprint}))


def test_resume_keeps_results_of_the_same_config_and_refuses_another(tmp_path):
    cfg = SuiteConfig(methods=["happo"], scenarios=["narrow_gate"], seeds=[0, 1], updates_per_run=3,
                      train_overrides=["algo.epochs=2"], out_dir=str(tmp_path / "s"))
    specs = plan(cfg)
    same = run_config(cfg, specs[0], Path(cfg.out_dir) / "runs" / specs[0].name).fingerprint()
    _fake_result(cfg, specs[0], same)
    check_resume(cfg, specs)          # the same settings resume: the kept result counts as done
    changed = SuiteConfig(**{**cfg.__dict__, "train_overrides": ["algo.epochs=3"]})
    with pytest.raises(ValueError, match="another config"):
        check_resume(changed, plan(changed))
    _fake_result(cfg, specs[1], "0" * 16)   # a result without this config's fingerprint
    with pytest.raises(ValueError, match="1 result"):
        check_resume(cfg, specs)


def test_pilot_is_the_protocols_own_runs_restricted(tmp_path):
    full = load_protocol(TABLE1, out_dir=str(tmp_path))
    pilot = load_protocol(TABLE1, pilot=True)
    assert {a.name for a in pilot.suite.arm_list()} == {"happo", "happo_cbf"}
    assert len(plan(pilot.suite)) == 2 * len(pilot.suite.scenarios) * len(pilot.suite.seeds) >= 18
    assert pilot.suite.out_dir.endswith("_pilot") and pilot.sha256 == full.sha256
    spec = plan(pilot.suite)[0]
    a = run_config(pilot.suite, spec, tmp_path / "a")
    b = run_config(full.suite, spec, tmp_path / "a")
    b.updates = a.updates
    assert a.fingerprint() == b.fingerprint()   # the same run as the campaign's, but for the budget
