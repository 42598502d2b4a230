"""The README's first lines are the two commands a new user runs; CI runs the same test command."""
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _readme_commands():
    lines = (ROOT / "README.md").read_text().splitlines()
    block = lines[lines.index("```bash") + 1:]
    return [line.split("#")[0].strip() for line in block[:2]]


def test_readme_opens_with_main_and_test_commands():
    main_cmd, test_cmd = _readme_commands()
    assert "sage train" in main_cmd and "pip install -e ." in main_cmd
    assert "pytest" in test_cmd and "[test]" in test_cmd


def _ci_commands():
    """.ci/run's command lines (comments and blank lines dropped)."""
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    return [line.strip() for line in ci if line.strip() and not line.strip().startswith("#")]


def test_ci_runs_the_readme_test_command_first_and_as_written():
    _, test_cmd = _readme_commands()
    lines = _ci_commands()
    assert test_cmd in lines, f"CI does not run the README's test command as written: {test_cmd}"
    at = lines.index(test_cmd)
    # nothing installs an optional extra before it: the README command runs on a fresh
    # machine without them, so CI must too
    before = lines[:at]
    assert not any("pip install" in line for line in before), before
    # its exit code is checked (pytest's 5, nothing collected, included), then the extras run
    assert lines[at + 1].startswith("check ") and "$?" in lines[at + 1]
    after = lines[at + 2:]
    assert any("pip install -e '.[cluster]'" in line for line in after)
    assert any("pytest" in line and "tests/test_ray.py" in line for line in after)
    assert "-eq 5" in (ROOT / ".ci" / "run").read_text()
