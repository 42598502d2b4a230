"""The learner's metrics row carries the policy lag of each update's data (learner version -
behaviour version), and an on-policy run (max_lag = 0) uses only data of the current version."""
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from services_fakes import FakeBatchEnv, FakeMethod, fake_propose, fake_solve  # noqa: E402

from services.config import TrainConfig  # noqa: E402
from deploy.threads import run_inprocess  # noqa: E402


@pytest.mark.parametrize("max_lag", [0, 1])
def test_metrics_rows_report_the_data_lag(tmp_path, max_lag):
    cfg = TrainConfig(run_id="lag", run_dir=str(tmp_path / "run"), updates=4, chunk_len=6, actors=2,
                      envs_per_actor=2, checkpoint_every=2, status_period_s=0.1, max_lag=max_lag).validate()
    out = run_inprocess(cfg, progress=False, method=FakeMethod(),
                        envs=[FakeBatchEnv(2, seed=0), FakeBatchEnv(2, seed=1)],
                        propose=fake_propose, solve=fake_solve, timeout_s=60)
    assert out["updates"] == 4
    rows = [json.loads(line) for line in (Path(cfg.run_dir) / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 4
    for row in rows:
        assert 0 <= row["lag_min"] <= row["lag_mean"] <= row["lag_max"] <= max_lag
    if max_lag == 0:
        assert all(r["lag_max"] == 0 and r["lag_mean"] == 0.0 for r in rows)
