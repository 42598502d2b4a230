"""The sage CLI assembles every area's subcommands without import errors."""
from sage.cli import COMMAND_MODULES, build_parser, main


def test_every_command_module_registers():
    for module in COMMAND_MODULES:
        assert callable(module.register), module.__name__
    parser = build_parser()
    commands = parser._subparsers._group_actions[0].choices
    assert {"train", "up", "eval", "suite", "report", "env", "tree", "trace", "audit", "export-bundle", "watch", "compare",
            "bench"} <= set(commands)
    bench = commands["bench"]._subparsers._group_actions[0].choices
    assert set(bench) == {"qp", "env", "scripted", "learner", "system", "scaling"}


def test_help_lists_core_commands(capsys):
    parser = build_parser()
    text = parser.format_help()
    for command in ("train", "eval", "bench", "env", "tree", "export-bundle"):
        assert command in text


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2


def test_train_overrides_reach_the_resolved_config(tmp_path):
    import pytest

    from sage.train import apply_override
    from services.config import TrainConfig

    cfg = TrainConfig()
    apply_override(cfg, "algo.actor_lr=0.0007")
    apply_override(cfg, "env.human_slot=2")
    apply_override(cfg, "shield.window_s=0.0005")
    assert cfg.algo_config().actor_lr == 0.0007 != TrainConfig().algo_config().actor_lr
    assert cfg.env_config().human_slot == 2
    assert cfg.shield.window_s == 0.0005
    with pytest.raises(SystemExit):
        apply_override(cfg, "shield.no_such_field=1")
    with pytest.raises(SystemExit):
        apply_override(cfg, "novalue")


def test_train_refuses_a_run_dir_of_another_method(tmp_path, capsys):
    import json

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"method": "sage", "scenario": "narrow_gate"}))
    assert main(["train", "--method", "happo", "--run-dir", str(run), "--updates", "1", "--quiet"]) == 2
    assert "holds a run of method 'sage'" in capsys.readouterr().err
