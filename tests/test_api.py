"""The Python API (sage/api.py): the same run directory and summary as `sage train`."""
import json

import pytest

from sage.api import TrainConfig, evaluate, train


def test_train_writes_the_cli_run_directory_and_returns_its_summary(tmp_path):
    cfg = TrainConfig(method="happo_cbf", updates=2, envs_per_actor=2, chunk_len=8, eval_episodes=1,
                      run_dir=str(tmp_path / "run"))
    run = train(cfg, overrides={"algo.epochs": 1, "seed": 3})
    assert cfg.seed == 0 and cfg.run_id == ""            # the caller's config is left as it was
    assert run.config.seed == 3 and run.config.algo.epochs == 1 and run.config.method == "happo_cbf"
    for name in ("config.json", "summary.json", "metrics.jsonl", "metrics.csv", "evaluated_params.npz"):
        assert (run.run_dir / name).exists(), name
    assert list((run.run_dir / "checkpoints").glob("ckpt_*.pt"))
    assert json.loads((run.run_dir / "summary.json").read_text())["eval"] == \
        json.loads(json.dumps(run.summary["eval"], default=float))
    assert run.summary["updates"] == 2
    saved = TrainConfig.load(run.run_dir / "config.json")
    assert saved == run.config
    rec = evaluate(run.run_dir, episodes=2)
    assert rec["method"] == "happo_cbf" and rec["episodes"] == 2 and rec["shielded"] is True
    assert evaluate(run.run_dir, episodes=1, shielded=False)["shielded"] is False


def test_bad_values_name_the_field():
    with pytest.raises(ValueError, match="actor_lr"):
        train(TrainConfig(), overrides={"algo.actor_lr": float("nan")})
    with pytest.raises(ValueError, match="no_such"):
        train(TrainConfig(), overrides={"algo.no_such": 1})
    with pytest.raises(ValueError, match="mode"):
        train(TrainConfig(), mode="ray")


def test_final_evaluation_over_the_last_checkpoints(tmp_path):
    import numpy as np

    cfg = TrainConfig(method="happo", updates=4, envs_per_actor=2, chunk_len=8, eval_episodes=2,
                      checkpoint_every=2, eval_checkpoints=2, run_dir=str(tmp_path / "run"))
    run = train(cfg)
    per = run.summary["eval_by_checkpoint"]
    assert [e["version"] for e in per] == [2, 4] and run.summary["eval"]["checkpoints"] == 2
    assert run.summary["eval"]["episodes_finished"] == 4
    for key in ("success_rate", "return_mean", "col_per_1k"):
        assert run.summary["eval"][key] == pytest.approx(np.mean([e[key] for e in per]))
    kept = np.load(run.run_dir / "evaluated_params.npz", allow_pickle=False)
    assert {k.split("/")[0] for k in kept.files} == {"v2", "v4"}
    with pytest.raises(ValueError, match="eval_checkpoints"):
        train(TrainConfig(eval_checkpoints=4, checkpoint_keep=3))
