"""The run config reaches the code one way: a saved file, flags and ``--set`` items
are kept exactly as given (good input survives), and every value outside its type,
finiteness or range is refused with one line (bad input refused)."""
from __future__ import annotations

import dataclasses
import json
import math
import typing

import pytest

from sage.cli import build_parser, main
from sage.train import config_from_args
from services.config import TrainConfig


def _args(argv):
    return build_parser().parse_args(["train", *argv])


def _saved(tmp_path, **fields) -> str:
    cfg = TrainConfig(run_id="saved-run", **fields)
    cfg.set("algo.actor_lr", 3e-4)
    cfg.set("env.max_steps", 123)
    cfg.set("actor.shield_timeout_s", 2.5)
    cfg.resolve()
    path = tmp_path / "config.json"
    cfg.save(path)
    return str(path)


def test_config_file_runs_exactly_as_saved(tmp_path):
    """The reported defect: a saved maze/happo/seed 7/4-env config trained sage on narrow_gate."""
    path = _saved(tmp_path, scenario="maze", method="happo", seed=7, envs_per_actor=4, updates=37)
    cfg = config_from_args(_args(["--config", path]))
    saved = TrainConfig.load(path)
    assert (cfg.scenario, cfg.method, cfg.seed, cfg.envs_per_actor, cfg.updates) == ("maze", "happo", 7, 4, 37)
    assert cfg.algo.actor_lr == 3e-4 and cfg.env.max_steps == 123 and cfg.actor.shield_timeout_s == 2.5
    assert json.loads(cfg.to_json()) == json.loads(saved.to_json())


def test_only_typed_flags_override_a_config_file(tmp_path):
    path = _saved(tmp_path, scenario="maze", method="happo", seed=7, envs_per_actor=4)
    cfg = config_from_args(_args(["--config", path, "--seed", "3", "--set", "algo.epochs=2"]))
    want = json.loads(TrainConfig.load(path).to_json())
    want["seed"], want["algo"]["seed"], want["algo"]["epochs"] = 3, 3, 2
    assert json.loads(cfg.to_json()) == want


def test_minutes_alone_lifts_the_update_budget_and_mode_follows_the_file(tmp_path):
    from services.config import UNLIMITED_UPDATES

    path = _saved(tmp_path, mode="supervised")
    cfg = config_from_args(_args(["--config", path, "--minutes", "2"]))
    assert cfg.minutes == 2.0 and cfg.updates == UNLIMITED_UPDATES and cfg.mode == "supervised"
    assert config_from_args(_args(["--config", path, "--mode", "inprocess"])).mode == "inprocess"


def test_fresh_run_gets_the_dataclass_defaults():
    cfg = config_from_args(_args([]))
    d = TrainConfig()
    for name in ("scenario", "method", "updates", "seed", "envs_per_actor", "chunk_len", "max_lag", "mode"):
        assert getattr(cfg, name) == getattr(d, name)


def _non_default_config() -> TrainConfig:
    cfg = TrainConfig(run_id="rt", scenario="tilt_gate", method="sail_cbf", actors=3, shields=2, seed=11,
                      minutes=1.5, checkpoint_keep=0)
    for path, value in (("transport.connect", ["tcp/127.0.0.1:7447"]), ("ports.learner", 9400),
                        ("shield.window_s", 0.0), ("actor.verify_tol", 1e-7), ("actor.pipeline", True),
                        ("env.human_slot", 2), ("env.grasp_solref", (0.05, 1.0)), ("env.reward.drop", 4.0),
                        ("env.max_steps", None), ("algo.talo_step", "direct"), ("algo.split_k", 0)):
        cfg.set(path, value)
    return cfg.resolve()


def test_round_trip_keeps_every_section():
    cfg = _non_default_config()
    again = TrainConfig.from_dict(json.loads(cfg.to_json()))
    assert again == cfg and again.fingerprint() == cfg.fingerprint()
    assert again.env.reward.drop == 4.0 and again.env.grasp_solref == (0.05, 1.0)


def test_fingerprint_is_what_is_computed_not_where():
    a = _non_default_config()
    b = dataclasses.replace(a, run_id="elsewhere", run_dir="/tmp/x", ports=dataclasses.replace(a.ports, learner=0))
    assert a.fingerprint() == b.fingerprint()
    c = TrainConfig.from_dict(json.loads(a.to_json()))
    c.set("algo.epochs", a.algo.epochs + 1)
    assert c.fingerprint() != a.fingerprint()


def _numeric_paths(obj, prefix=""):
    hints = typing.get_type_hints(type(obj))
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from _numeric_paths(value, prefix + f.name + ".")
        elif float in typing.get_args(hints[f.name]) or hints[f.name] is float:
            yield prefix + f.name


def test_every_float_field_refuses_nan_and_inf():
    paths = [p for p in _numeric_paths(TrainConfig()) if p not in ("env.scenario",)]
    assert len(paths) > 40
    for path in paths:
        for bad in (math.nan, math.inf, -math.inf):
            cfg = TrainConfig(run_id="t")
            with pytest.raises(ValueError, match=path.split(".")[-1]):
                cfg.set(path, bad)
                cfg.resolve()


def test_shield_backends_listed_in_the_config_are_the_solvers():
    from common.shield.qp import BACKENDS

    field = {f.name: f for f in dataclasses.fields(TrainConfig().shield)}["backend"]
    assert set(field.metadata["choices"]) == {"default", *BACKENDS}


@pytest.mark.parametrize("patch, needle", [
    ('"actor": {"shield_timeout_s": Infinity}', "Infinity is not a valid config value"),
    ('"envs_per_actor": 1000000000', "envs_per_actor"),
    ('"chunk_len": 1000000000', "chunk_len"),
    ('"shield": {"window_s": NaN}', "NaN is not a valid config value"),
    ('"actor": {"shield_timeout_s": 1e9}', "shield_timeout_s"),
])
def test_config_values_that_would_crash_loop_a_run_exit_2(tmp_path, capsys, patch, needle):
    path = tmp_path / "bad.json"
    path.write_text("{" + f'"run_id": "bad", {patch}' + "}")
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--config", str(path)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0] and "Traceback" not in err[0]


def test_deeply_nested_config_is_one_line(tmp_path, capsys):
    path = tmp_path / "deep.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--config", str(path)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nested too deeply" in err[0]


def test_set_reaches_nested_and_frozen_sections():
    from sage.train import apply_override

    cfg = TrainConfig()
    apply_override(cfg, "env.reward.collision=2.5")
    apply_override(cfg, "actor.trace_every=10")
    apply_override(cfg, "train.deploy_probe_every=7")
    assert cfg.env.reward.collision == 2.5 and cfg.actor.trace_every == 10 and cfg.deploy_probe_every == 7
    for bad in ("env.reward.nope=1", "actor.verify_tol=1.0", "shield.window_s=nan", "train.updates=0"):
        with pytest.raises((SystemExit, ValueError)):
            apply_override(cfg, bad)
            cfg.resolve()


def test_resume_into_a_run_of_another_config_is_refused(tmp_path, capsys):
    run_dir = tmp_path / "r"
    TrainConfig(run_id="r", run_dir=str(run_dir)).resolve().save(run_dir / "config.json")
    assert main(["train", "--run-dir", str(run_dir), "--set", "algo.tree_depth=3", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "algo.tree_depth 4 there, 3 now" in err
