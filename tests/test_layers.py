"""The layering of docs/architecture.md, as import-linter contracts in
pyproject.toml: app (sage) > deploy > services > common, and the layers
inside common, services and deploy. The second test plants a forbidden import
(and a torch import in the torch-free registry, and a production import of a kernel's numpy
reference) in a copy of the tree and checks
that the contracts catch them."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINT = [sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command; "
                              "sys.exit(lint_imports_command())"]


def _lint(root: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(root))
    return subprocess.run(LINT + ["--config", str(root / "pyproject.toml"), "--no-cache"], cwd=root, env=env,
                          capture_output=True, text=True, timeout=300)


def test_import_contracts_hold():
    proc = _lint(ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "0 broken" in proc.stdout


def test_a_forbidden_import_breaks_a_contract(tmp_path):
    for pkg in ("common", "services", "deploy", "sage"):
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    wire = tmp_path / "common" / "wire.py"
    wire.write_text(wire.read_text() + "\nfrom services.config import TrainConfig  # noqa: E402,F401\n")
    registry = tmp_path / "common" / "algos" / "registry.py"   # indirectly, through another module
    registry.write_text(registry.read_text() + "\nfrom common.algos import critic  # noqa: E402,F401\n")
    rollout = tmp_path / "common" / "policy" / "rollout.py"   # a reference is a test oracle, not a code path
    rollout.write_text(rollout.read_text() + "\nfrom common.policy import reference  # noqa: E402,F401\n")
    proc = _lint(tmp_path)
    assert proc.returncode != 0
    assert "app > deploy > services > common BROKEN" in proc.stdout
    assert "common.wire -> services.config" in proc.stdout
    assert "torch-free: the method registry and the learner config BROKEN" in proc.stdout
    assert "common.algos.registry -> common.algos.critic" in proc.stdout
    assert "kernel references: imported by tests only BROKEN" in proc.stdout
    assert "common.policy.rollout -> common.policy.reference" in proc.stdout


def test_every_module_has_a_tier():
    """tests/conftest.py places each test module in one tier (unit / sweep / integration / system)."""
    from pathlib import Path

    from conftest import TIERS

    modules = {p.stem[len("test_"):] for p in Path(__file__).parent.glob("test_*.py")}
    placed = [name for names in TIERS.values() for name in names]
    assert len(placed) == len(set(placed)), "a module in two tiers"
    assert modules == set(placed), (f"without a tier: {sorted(modules - set(placed))}; "
                                    f"gone: {sorted(set(placed) - modules)}")
