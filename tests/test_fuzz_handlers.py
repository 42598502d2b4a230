"""Coverage-guided fuzzing of the services' message handlers (tests/fuzz_handlers.py,
atheris), bounded in runs and time, with a corpus of real messages; skipped where
atheris is not installed (the `test` extra installs it)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("atheris")

ROOT = Path(__file__).resolve().parents[1]
HARNESS = ROOT / "tests" / "fuzz_handlers.py"


@pytest.mark.slow
def test_no_message_makes_a_handler_raise(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    corpus = tmp_path / "corpus"
    subprocess.run([sys.executable, str(HARNESS), "--write-corpus", str(corpus)], env=env, check=True, timeout=300)
    assert sorted(p.name for p in corpus.iterdir()) == ["params", "shield_rep", "shield_req", "status", "traj"]
    res = subprocess.run([sys.executable, str(HARNESS), "-runs=100000", "-max_total_time=60", str(corpus)],
                         env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    tail = "\n".join(line for line in res.stderr.splitlines() if not line.startswith("INFO: Instrumenting"))[-3000:]
    assert res.returncode == 0, tail              # a raising handler is a libFuzzer crash: non-zero exit
    assert "Done " in res.stderr and not list(tmp_path.glob("crash-*")), tail
