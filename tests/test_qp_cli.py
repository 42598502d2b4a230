"""`sage bench qp` prints the JSON the issue asks for (tiny batch, no timing asserts)."""
import json

from sage.cli import main


def test_bench_qp_json(capsys):
    assert main(["bench", "qp", "--json", "--batch", "8", "--rows", "12", "--repeats", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["default_backend"] in out["backends"]
    assert set(out["backends"]) >= {"dual_active_set", "osqp"}
    assert all(us > 0 for us in out["backends"].values())
    assert out["osqp_loop_us_per_qp"] > 0
    assert out["max_abs_diff"] <= 1e-6
    assert "osqp_loop_over_default" in out["ratios"]
    assert out["numba_compile_excluded"] is True
    assert out["instances"]["batch"] == 8 and out["instances"]["rows"] == 12


def test_bench_qp_text(capsys):
    assert main(["bench", "qp", "--batch", "4", "--rows", "6", "--repeats", "1"]) == 0
    text = capsys.readouterr().out
    assert "fresh OSQP loop" in text and "(default)" in text
