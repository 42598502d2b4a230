"""The base layer's shared pieces: SafetyRows, the run-directory layout and its
atomic / torn-line-tolerant file access, the one launcher's member list, and
TrainConfig's typed env/algo sections."""
from __future__ import annotations

import json

import numpy as np
import pytest

from common.rundir import RunDir, atomic_write_text, read_jsonl
from common.safety_rows import SafetyRows
from common.shield.qp import shield_actions, solve_cbf_qp
from common.shield.random_problems import random_cbf_problems
from services.config import TrainConfig
from services.launcher import Member, entry_argv, run_members


def _rows(B=5, seed=0):
    a, C, c, _ = random_cbf_problems(np.random.default_rng(seed), B)
    return a, SafetyRows(C, c, np.ones(c.shape, bool), np.zeros(a.shape, bool))


def test_safety_rows_feed_the_qp_like_the_arrays():
    a, rows = _rows()
    got = shield_actions(a, rows)
    ref = solve_cbf_qp(a, rows.C, rows.c, rows.row_mask, rows.fixed_mask)
    np.testing.assert_array_equal(got.a_exec, ref.a_exec)
    step = {**rows.as_dict(), "obs": np.zeros(1)}        # an env output holds more than the rows
    assert all(getattr(SafetyRows.of(step), k) is getattr(rows, k) for k in SafetyRows.FIELDS)  # held, not copied


def test_safety_rows_select_concat_residual():
    a, rows = _rows(6)
    parts = [rows.select(slice(0, 2)), rows.select(slice(2, 6))]
    both = SafetyRows.concat(parts)
    for k in SafetyRows.FIELDS:
        np.testing.assert_array_equal(getattr(both, k), getattr(rows, k))
    masked = SafetyRows(rows.C, rows.c, rows.row_mask.copy(), rows.fixed_mask)
    masked.row_mask[:, 0] = False
    r = masked.residual(a)
    assert np.all(np.isneginf(r[:, 0]))
    np.testing.assert_allclose(r[:, 1:], rows.c[:, 1:] - np.einsum("bmd,bd->bm", rows.C[:, 1:], a))


def test_rundir_names_and_torn_jsonl(tmp_path):
    run = RunDir(tmp_path / "r")
    assert run.config.name == "config.json" and run.checkpoints.name == "checkpoints"
    assert run.log("actor-2") == run.logs / "actor-2.log"
    atomic_write_text(run.metrics_jsonl, json.dumps({"update": 1}) + "\n" + json.dumps({"update": 2}) + "\n")
    with open(run.metrics_jsonl, "a") as f:
        f.write('{"update": 3, "env_ste')          # a learner killed mid-line
    assert [r["update"] for r in read_jsonl(run.metrics_jsonl)] == [1, 2]
    assert read_jsonl(run.root / "missing.jsonl") == []
    assert not list(run.root.glob(".*.tmp"))       # the atomic write left no temporary file


def test_launcher_members_and_entry_points():
    members = run_members([0, 3])
    assert [m.name for m in members] == ["shield", "learner", "actor-0", "actor-3"]
    assert entry_argv(Member("actor", 3), "RUN.json", python="py") == [
        "py", "-m", "services.actor", "--config", "RUN.json", "--actor-id", "3"]
    assert [m.name for m in run_members([1], roles=("actor",))] == ["actor-1"]
    with pytest.raises(ValueError, match="unknown roles"):
        run_members([0], roles=("planner",))


def test_train_config_env_and_algo_are_typed_and_follow_the_run():
    cfg = TrainConfig(scenario="maze", seed=7, env={"max_steps": 50}, algo={"epochs": 2})
    assert cfg.env.max_steps == 50 and cfg.algo.epochs == 2
    cfg.scenario, cfg.seed = "chicane", 3                 # e.g. flags applied after loading a config
    assert cfg.env_config().scenario == "chicane" and cfg.algo_config().seed == 3
    cfg.override("env", "human_slot", 1)
    assert cfg.env_config().human_slot == 1
    with pytest.raises(ValueError):
        cfg.override("algo", "no_such_field", 1)
    with pytest.raises(ValueError, match="follows the run"):
        cfg.override("algo", "seed", 5)
    again = TrainConfig.from_dict(json.loads(cfg.resolve().to_json()))
    assert again.env == cfg.env and again.algo == cfg.algo
