"""What a user meets on day one (issue 28, item 7): the live line's n/N and ETA,
a resumed run saying so, `sage up` writing summary.json with the final
evaluation like `sage train`, help texts that match what the commands do, and
the README naming every method."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from common.algos.registry import ALL_METHODS
from common.status import StatusBoard, status_line
from sage.cli import build_parser, main
from services.config import TrainConfig

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--envs-per-actor", "2", "--chunk-len", "8", "--metrics-port", "0"]


def _learner(updates, budget, progress, pid=7, state="running"):
    return {"role": "learner", "id": "0", "state": state, "pid": pid, "version": updates + 1, "updates": updates,
            "env_steps_per_s": 0.0, "success_rate": None, "shield_p99_s": None,
            "extra": {"budget_updates": float(budget), "progress": progress}}


def test_status_line_shows_updates_out_of_the_budget_and_the_eta():
    line = status_line({}, {"learner/0": _learner(37, 100, 0.37)}, eta_s=65.0)
    assert line.startswith("update 37/100 (37%), ETA 1m05s | steps/s"), line
    # a --minutes budget: no update budget to show, the share of the minutes is the progress
    line = status_line({}, {"learner/0": _learner(37, 10**9, 0.40)})
    assert line.startswith("update 37 (40%), ETA - | steps/s"), line
    assert status_line({}).startswith("steps/s")   # no learner heard from yet: nothing to show


def test_status_board_eta_from_the_progress_rate_and_a_restarted_learner():
    clock = [100.0]
    board = StatusBoard("r", stale_after_s=1e9, clock=lambda: clock[0])

    def heard(body):
        board.latest["learner/0"] = dict(body, received=clock[0])

    heard(_learner(20, 100, 0.2))
    assert board.eta() is None                       # one observation: no rate yet
    clock[0] = 110.0
    heard(_learner(30, 100, 0.3))
    assert board.eta() == pytest.approx(70.0)        # 0.1 per 10 s, 0.7 left
    assert "update 30/100 (30%), ETA 1m10s" in board.line()
    clock[0] = 120.0
    heard(_learner(30, 100, 0.3, pid=8))              # a restarted learner: measured afresh
    assert board.eta() is None
    heard(_learner(100, 100, 1.0, pid=8))
    assert board.eta() == 0.0


def test_tiny_run_prints_n_of_n_and_a_resumed_run_says_from_which_version(tmp_path, capsys):
    run = tmp_path / "r"
    args = ["train", "--method", "happo_cbf", "--eval-episodes", "0", "--run-dir", str(run), *TINY]
    assert main(args + ["--updates", "2"]) == 0
    err = capsys.readouterr().err
    assert "update 2/2 (100%), ETA 0s" in err, err   # the final live line (a plain line: not a terminal)
    assert "resuming" not in err
    assert main(args + ["--updates", "4"]) == 0
    err = capsys.readouterr().err
    m = re.search(r"resuming run \S+ from checkpoint version (\d+) \(update 2 of 4, \d+ env steps\)", err)
    assert m, err
    summary = json.loads((run / "summary.json").read_text())
    assert summary["resumed_from"] == int(m.group(1)) and summary["updates"] == 4
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines() if x.strip()]
    assert [r["update"] for r in rows] == [1, 2, 3, 4]


@pytest.mark.slow
def test_sage_up_writes_summary_and_final_evaluation_like_sage_train(tmp_path):
    run = tmp_path / "up"
    cfg = TrainConfig(run_id="uptest", run_dir=str(run), method="happo_cbf", actors=1, envs_per_actor=2,
                      chunk_len=8, updates=2, eval_episodes=1, checkpoint_every=1, deploy_probe_every=0,
                      status_period_s=0.25, algo={"epochs": 1, "minibatches": 1, "critic_hidden": 32})
    path = cfg.resolve().save(run / "config.json")
    proc = subprocess.run([sys.executable, "-m", "sage", "up", "--config", str(path)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["mode"] == "supervised" and summary["updates"] == 2 and summary["version"] >= 2
    assert summary["eval"]["episodes_finished"] == 1 and summary["eval"]["shielded"] is True
    assert "eval (1 episodes on 1 checkpoint(s), shielded)" in proc.stderr


def _option(command: str, flag: str):
    sub = next(a for a in build_parser()._actions if getattr(a, "choices", None) and command in a.choices)
    return next(a for a in sub.choices[command]._actions if flag in a.option_strings or a.dest == flag)


def test_help_texts_say_what_the_commands_do():
    assert "JSON" in (_option("eval", "--json").help or "")
    out_help = _option("tree", "--out").help
    assert "required" not in out_help and "tree_carrier<N>" in out_help


def test_tree_show_png_without_out_writes_the_default_file_its_help_names(tmp_path, monkeypatch, capsys):
    from common.algos import AlgoConfig, make_method
    from common.env.batch_env import BatchEnv

    params = make_method("sage", AlgoConfig(), BatchEnv.obs_dim, 0).policy_params()
    np.savez(tmp_path / "params.npz", **params)
    monkeypatch.chdir(tmp_path)
    assert main(["tree", "show", str(tmp_path / "params.npz"), "--carrier", "1", "--format", "png"]) == 0
    assert capsys.readouterr().out.strip() == "tree_carrier1.png"
    assert (tmp_path / "tree_carrier1.png").stat().st_size > 1000


def test_readme_method_list_names_every_method():
    text = (ROOT / "README.md").read_text()
    methods = text[text.index("Methods: "):text.index("Scenarios: ")]
    for name in ALL_METHODS:
        assert f"`{name}`" in methods, name
