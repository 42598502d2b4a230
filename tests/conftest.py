"""Shared fixtures, and the test tiers.

Every test module belongs to one tier (``pyproject.toml`` declares the markers):

- ``unit``: pure functions and single objects, no threads, no processes;
- ``sweep``: unit scope, but long by design: fuzz loops, property runs of hundreds
  of examples, learning curves, a kernel checked against its twin on every scenario,
  every figure of a report drawn;
- ``integration``: services as threads in one process (an in-process bus, a tiny run);
- ``system``: real processes, routers, Ray, network namespaces.

``pytest -m unit`` is the quick loop while editing (``-m "unit or sweep"``: all of unit
scope); CI runs every tier. A new test module must be placed in ``TIERS``
(``test_every_module_has_a_tier`` in tests/test_layers.py fails otherwise); one long
test of a unit module carries ``@pytest.mark.sweep`` and leaves the quick loop alone.
"""
import time

import pytest

TIERS = {
    "unit": {
        "algos", "algos_critic", "algos_env", "audit_stats", "audit_trace", "audit_tree",
        "base_modules", "bench_scaling", "compare", "driver", "env", "env_fast", "env_kernels", "files_are_data",
        "gap_closed_form",
        "graded_outcomes", "instrument", "kernels_nogil", "mechanism_metrics", "outcome_metrics", "parallel_env",
        "payload_points", "progress", "proposal", "proposal_kernels", "protocol", "qp", "qp_cli",
        "readme", "report", "report_ci", "row_kernels", "safety", "safety_honesty", "safety_kkt",
        "safety_profiles", "sail", "sail_kernel", "sparse_tree", "stats", "surrogate_chain", "talo", "talo_fast",
        "tree", "tree_grad_kernels", "tree_kernel", "wire",
    },
    "sweep": {"algos_learning", "qp_properties", "wire_fuzz"},
    "integration": {
        "actor_pruned_rows", "api", "checkpoint", "cli", "config", "env_layouts", "hostile", "human_slot",
        "pacing", "pipeline_shards", "policy_lag", "reconciliation", "services", "shield_budgets", "shield_prune",
        "suite_eval", "tensorboard", "thread_placement", "tracking", "transport_limits", "video",
    },
    "system": {
        "adam", "bench_learner", "bench_system", "bundle", "cli_errors", "day_one", "faults", "fuzz_handlers", "layers",
        "multihost", "ray", "rollout", "supervisor", "tls_acl", "trace_stream",
    },
}
TIER_OF = {f"test_{name}": tier for tier, names in TIERS.items() for name in names}


def pytest_collection_modifyitems(config, items):
    for item in items:
        tier = TIER_OF.get(item.module.__name__.rsplit(".", 1)[-1]) if item.module is not None else None
        if tier == "unit" and item.get_closest_marker("sweep") is not None:
            continue   # a sweep of a unit module: its own mark is its tier
        if tier is not None:
            item.add_marker(getattr(pytest.mark, tier))


def wait_for(pred, timeout: float = 10.0, what: str = "the condition", poll: float = 0.02):
    """``pred()``'s first true value, polled every ``poll`` s; AssertionError after ``timeout`` s.
    (``from conftest import wait_for``: pytest puts this folder on ``sys.path``.)"""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(poll)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """One real, tiny ``sage train`` run directory (sage, one update, one evaluation
    episode), trained once for every module that reads a run."""
    from sage.cli import main

    run = tmp_path_factory.mktemp("run") / "r"
    code = main(["train", "--method", "sage", "--updates", "1", "--envs-per-actor", "2",
                 "--chunk-len", "8", "--eval-episodes", "1", "--run-dir", str(run), "--quiet"])
    assert code == 0
    return run


@pytest.fixture
def bus():
    """A network-less Zenoh session (the in-process placement's bus)."""
    from common.transport import Bus

    b = Bus.open(inprocess=True)
    yield b
    b.close()


@pytest.fixture
def one_torch_thread():
    """2 shared CPU cores: torch intra-op threads only oversubscribe."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
