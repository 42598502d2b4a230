"""`sage train --human-slot 1` (a README command) for every method at a tiny budget:
the scripted human's block is exogenous (fixed in the QP, no tree, no proposal density),
and its measured action often sits on the box face (|a| = 1)."""
import json

import pytest

from common.algos.registry import ALL_METHODS
from sage.cli import main


@pytest.mark.parametrize("method", ALL_METHODS)
def test_train_with_a_human_partner_runs_every_method(method, tmp_path, capsys):
    run = tmp_path / "r"
    code = main(["train", "--method", method, "--human-slot", "1", "--updates", "2", "--envs-per-actor", "2",
                 "--chunk-len", "16", "--eval-episodes", "1", "--metrics-port", "0", "--run-dir", str(run), "--quiet"])
    assert code == 0, capsys.readouterr().err[-2000:]
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["method"] == method and cfg["env"]["human_slot"] == 1
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines() if x.strip()]
    assert [r["update"] for r in rows] == [1, 2]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["updates"] == 2 and summary["eval"]["episodes_finished"] == 1
