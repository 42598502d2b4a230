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


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    _, test_cmd = _readme_commands()
    for part in test_cmd.split(" && "):
        assert part.strip() in ci, f"CI does not run README step: {part}"
