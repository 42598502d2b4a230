"""The sage CLI assembles every area's subcommands without import errors."""
from common.cli import COMMAND_MODULES, build_parser, main


def test_every_area_module_registers():
    import importlib

    for name in COMMAND_MODULES:
        module = importlib.import_module(name)
        assert callable(module.register), name


def test_help_lists_core_commands(capsys):
    parser = build_parser()
    text = parser.format_help()
    for command in ("train", "eval", "bench", "env", "tree", "export-bundle"):
        assert command in text


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2
