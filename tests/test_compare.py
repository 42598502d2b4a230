"""sage compare: variants of one setting from suite result dirs, with intervals."""
import json

import pytest

from sage.cli import main
from sage.compare import variant_rows, wilson


def write_suite(folder, srs, override, method="sage"):
    folder.mkdir(parents=True, exist_ok=True)
    for (scenario, seed), sr in srs.items():
        ev = {"success_rate": sr, "episodes": 100, "margin_col_per_1k": 1.0, "col_per_1k": 0.0,
              "correction": 0.1, "intervention_rate": 0.2}
        (folder / f"{method}__{scenario}__seed{seed}.json").write_text(json.dumps(
            {"method": method, "scenario": scenario, "seed": seed, "eval": ev, "train_curve": [],
             "budget": {"overrides": [override]}}))
    (folder / "suite_config.json").write_text("{}")


def test_wilson_matches_the_textbook_interval():
    lo, hi = wilson(0, 10)
    assert lo == pytest.approx(0.0, abs=1e-12) and hi == pytest.approx(0.2775, abs=1e-4)
    lo, hi = wilson(50, 100)
    assert lo == pytest.approx(0.4038, abs=1e-4) and hi == pytest.approx(0.5962, abs=1e-4)


def test_variant_rows_pool_runs_and_stratify_by_scenario(tmp_path, capsys):
    write_suite(tmp_path / "a", {("g", 0): 1.0, ("g", 1): 0.8, ("c", 0): 0.6, ("c", 1): 0.6}, "algo.split_k=0")
    write_suite(tmp_path / "b", {("g", 0): 1.0, ("g", 1): 1.0, ("c", 0): 1.0, ("c", 1): 1.0}, "algo.split_k=1")
    (row,) = variant_rows("a", tmp_path / "a")
    assert row["runs"] == 4 and row["success_rate"] == pytest.approx(0.75) and row["episodes"] == 400
    assert row["per_scenario_sr"] == {"c": pytest.approx(0.6), "g": pytest.approx(0.9)}
    lo, hi = row["success_rate_ci"]
    assert 0.6 <= lo <= 0.75 <= hi <= 0.9 + 1e-9     # mean of per-scenario means, resampled within each
    assert row["overrides"] == ["algo.split_k=0"]
    assert main(["compare", f"dense={tmp_path / 'a'}", f"k1={tmp_path / 'b'}"]) == 0
    text = capsys.readouterr().out
    assert "| dense | SAGE+CBF | 4 |" in text and "| k1 | SAGE+CBF | 4 |" in text and "SR c" in text
    with pytest.raises(SystemExit) as e:
        main(["compare", f"x={tmp_path / 'missing'}"])
    assert e.value.code == 2


def test_a_suite_of_several_methods_gives_one_row_per_method(tmp_path, capsys):
    """Regression: every method of a suite was pooled into one row."""
    write_suite(tmp_path / "s", {("g", 0): 1.0, ("g", 1): 0.8}, "x=1", method="sage")
    write_suite(tmp_path / "s", {("g", 0): 0.2, ("g", 1): 0.0}, "x=1", method="happo")
    rows = variant_rows("v", tmp_path / "s")
    assert [(r["method"], r["runs"]) for r in rows] == [("happo", 2), ("sage", 2)]
    assert rows[0]["success_rate"] == pytest.approx(0.1) and rows[1]["success_rate"] == pytest.approx(0.9)
    assert rows[0]["episodes"] == rows[1]["episodes"] == 200
    assert main(["compare", f"v={tmp_path / 's'}", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [(r["variant"], r["method"]) for r in out] == [("v", "happo"), ("v", "sage")]
    assert main(["compare", f"v={tmp_path / 's'}"]) == 0
    text = capsys.readouterr().out
    assert "| v | HAPPO | 2 |" in text and "| v | SAGE+CBF | 2 |" in text
