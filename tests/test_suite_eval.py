"""sage train -> sage eval -> sage suite -> sage report on a tiny real run."""
import json
from pathlib import Path

import pytest

from sage.cli import main
from sage.report import EVAL_KEYS


def test_eval_reads_newest_checkpoint(tiny_run, capsys):
    assert main(["eval", str(tiny_run), "--episodes", "2", "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["method"] == "sage" and rec["episodes"] == 2 and rec["shielded"] is True
    for key in EVAL_KEYS:
        assert key in rec
    assert 0.0 <= rec["proposal_violation"] <= 1.0


def test_eval_records_traces_for_the_audit(tiny_run, tmp_path, capsys):
    from common.audit.recording import Recording

    out = tmp_path / "rec.npz"
    assert main(["eval", str(tiny_run), "--episodes", "3", "--record", str(out), "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    # the recording holds the very episodes that were scored (one deployment loop, run once)
    recording = Recording.load(out)
    metrics = recording.meta["episode_metrics"]
    assert len(metrics) == 3 and rec["episodes"] == 3
    assert sum(m["success"] for m in metrics) / 3 == pytest.approx(rec["success_rate"])
    assert recording.n_steps == sum(m["steps"] for m in metrics)
    assert main(["audit", str(out), "--out", str(tmp_path / "audit")]) == 0


@pytest.mark.slow
def test_suite_runs_reports_and_resumes(tmp_path):
    from sage.report import write_report
    from sage.suite import SuiteConfig, run_suite

    cfg = SuiteConfig(methods=["happo"], scenarios=["narrow_gate"], seeds=[0], minutes_per_run=5.0,
                      updates_per_run=2, eval_episodes=1, envs_per_actor=2, workers=1,
                      out_dir=str(tmp_path / "suite"))
    written = run_suite(cfg, log=lambda *_: None)
    assert len(written) == 1
    result = json.loads(written[0].read_text())
    assert result["method"] == "happo" and set(EVAL_KEYS) <= set(result["eval"])
    # the sample budget ended the run, not the 5-minute cap
    summary = json.loads((Path(result["run_dir"]) / "summary.json").read_text())
    assert summary["updates"] == 2 and result["budget"]["updates"] == 2
    assert run_suite(cfg, log=lambda *_: None) == []  # resumable: nothing left to run
    report = write_report(written, tmp_path / "report")
    assert report["runs"] == 1


def test_eval_accepts_a_checkpoint_file(tiny_run, capsys):
    ckpt = sorted((tiny_run / "checkpoints").glob("ckpt_*.pt"))[-1]
    assert main(["eval", str(ckpt), "--episodes", "1", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["method"] == "sage"


def test_proposal_violation_is_split_by_row_kind():
    import dataclasses

    from common.evaluation.deployment import evaluate_policy
    from services.config import TrainConfig
    from services.learner.service import build_method

    cfg = TrainConfig(run_id="t", method="sage").resolve()
    params = build_method(cfg).policy_params()   # untrained trees: most proposals violate a row
    res = evaluate_policy(params, cfg.env_config(), 2, seed=3, shielded=True, max_steps=40)
    by_kind = res["proposal_violation_by_kind"]
    # the default "paper" row profile has no formation rows, so no formation kind to count
    assert res["safety_rows"] == "paper" and set(by_kind) == {"carrier_wall", "payload_wall", "any_wall"}
    assert by_kind["any_wall"] == res["proposal_violation_rate"]
    assert "margin_col_per_1k" in res and res["margin_violation_steps"] >= 0
    grasp = evaluate_policy(params, dataclasses.replace(cfg.env_config(), safety_rows="grasp"), 2, seed=3,
                            shielded=True, max_steps=40)
    by_kind = grasp["proposal_violation_by_kind"]
    assert set(by_kind) == {"carrier_wall", "payload_wall", "formation", "any_wall"}
    assert all(0.0 <= v <= 1.0 for v in by_kind.values())
    # a step violates some row iff it violates a row of some kind
    kinds = [by_kind[k] for k in ("carrier_wall", "payload_wall", "formation")]
    assert max(kinds) <= grasp["proposal_violation_rate"] <= sum(kinds) + 1e-12
    assert max(kinds[:2]) <= by_kind["any_wall"] <= sum(kinds[:2]) + 1e-12
    assert grasp["proposal_violation_rate"] > 0


def test_eval_beside_a_human_partner_holds_the_human_block(tiny_run, capsys):
    """`sage eval --human-slot k`: the robot-trained trees drive the other slots and
    the QP never moves the human's (exogenous) block."""
    assert main(["eval", str(tiny_run), "--episodes", "2", "--human-slot", "1", "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["human_slot"] == 1 and rec["episodes"] == 2 and rec["shielded"] is True
    assert main(["eval", str(tiny_run), "--episodes", "1", "--human-slot", "none", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["human_slot"] is None


def test_evaluation_with_a_human_never_corrects_the_human_block(monkeypatch):
    import dataclasses

    import common.shield.qp as qp
    from common.evaluation.deployment import evaluate_policy
    from services.config import TrainConfig
    from services.learner.service import build_method

    cfg = TrainConfig(run_id="t", method="sage").resolve()
    params = build_method(cfg).policy_params()
    seen = []
    real = qp.solve_cbf_qp

    def spy(a, C, c, mask, fixed, **kw):
        res = real(a, C, c, mask, fixed, **kw)
        seen.append((fixed.copy(), a.copy(), res.a_exec.copy()))
        return res

    monkeypatch.setattr(qp, "solve_cbf_qp", spy)
    env_cfg = dataclasses.replace(cfg.env_config(), human_slot=2)
    evaluate_policy(params, env_cfg, 2, seed=5, shielded=True, max_steps=15)
    assert seen
    for fixed, a, a_exec in seen:
        assert fixed[:, 6:9].all() and not fixed[:, :6].any()   # slot 2 = action dims 6..8
        assert (a_exec[fixed] == a[fixed]).all()


def test_learner_logs_a_deterministic_deployment_probe(tmp_path):
    """--set train.deploy_probe_every=1: each update's row carries what deployment
    would do now (hard trees + exact QP on held-out episodes)."""
    run = tmp_path / "probe"
    assert main(["train", "--method", "happo_cbf", "--updates", "2", "--envs-per-actor", "2", "--chunk-len", "8",
                 "--eval-episodes", "0", "--set", "train.deploy_probe_every=1", "--set", "train.deploy_probe_episodes=2",
                 "--set", "env.max_steps=5", "--run-dir", str(run), "--quiet"]) == 0
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 2
    for r in rows:
        assert 0.0 <= r["deploy_sr"] <= 1.0 and r["deploy_correction"] >= 0.0
        assert r["deploy_col_per_1k"] >= 0.0 and "deploy_return" in r


def test_set_train_field_is_checked():
    from sage.train import apply_override
    from services.config import TrainConfig

    cfg = TrainConfig()
    apply_override(cfg, "train.deploy_probe_every=7")
    assert cfg.deploy_probe_every == 7
    with pytest.raises(SystemExit, match="unknown config field"):
        apply_override(cfg, "train.no_such_field=1")
    with pytest.raises(SystemExit, match="unknown config field"):
        apply_override(cfg, "train.shield=1")       # nested sections go through shield.KEY


def test_eval_reports_what_differs_from_training(tiny_run, capsys):
    """`sage eval` says, before evaluating, which flags change the run's saved
    configuration, and puts the same in its JSON."""
    assert main(["eval", str(tiny_run), "--episodes", "1", "--json"]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["differs_from_training"] == {} and "sage eval:" not in cap.err
    assert main(["eval", str(tiny_run), "--episodes", "1", "--scenario", "tilt_gate", "--unshielded",
                 "--human-slot", "1", "--json"]) == 0
    cap = capsys.readouterr()
    notice = [line for line in cap.err.splitlines() if line.startswith("sage eval:")]
    assert notice == ["sage eval: evaluating on tilt_gate (trained on narrow_gate); with a human in slot 1 "
                      "(trained with three robots); unshielded (trained shielded)"]
    rec = json.loads(cap.out)
    assert rec["differs_from_training"] == {
        "scenario": {"eval": "tilt_gate", "trained": "narrow_gate"},
        "human_slot": {"eval": 1, "trained": None},
        "shielded": {"eval": False, "trained": True}}
    assert rec["scenario"] == "tilt_gate" and rec["shielded"] is False and rec["human_slot"] == 1


def test_eval_differences_of_an_unshielded_method():
    from sage.evaluate import differences_notice, training_differences
    from services.config import TrainConfig

    cfg = TrainConfig(run_id="t", method="happo").resolve()
    diff = training_differences(cfg.env_config(), cfg.method, cfg.env_config(), shielded=True)
    assert diff == {"shielded": {"eval": True, "trained": False}}
    assert differences_notice(diff) == "sage eval: shielded (trained unshielded)"
    assert training_differences(cfg.env_config(), cfg.method, cfg.env_config(), shielded=False) == {}
    assert differences_notice({}) is None
