"""sage instrument: graded runs, the protocol's stopping rule and the power table on made-up records."""
import json

import pytest

from sage import instrument
from sage.cli import main


def _rec(arm, scenario, seed, sr, curve=(), dr=0.0, col=0.0):
    return {"method": arm, "scenario": scenario, "seed": seed,
            "eval": {"success_rate": sr, "drop_rate": dr, "col_per_1k": col},
            "train_curve": [{"update": u, "success_rate": v} for u, v in curve], "budget": {}}


def test_graded_counts_runs_strictly_inside_5_and_95_percent():
    recs = [_rec("happo", "a", k, sr) for k, sr in enumerate([0.0, 0.05, 0.06, 0.5, 0.94, 0.95, 1.0])]
    assert instrument.graded_runs(recs)["graded"] == 3


def test_stopping_rule_finds_the_plateau():
    # success rises linearly to 0.8 at update 100, then stays; the window of updates 81-100 averages
    # 0.724 (> 0.05 below the later 0.8), so the plateau is the window ending at 120
    curve = [(u, min(0.8, 0.008 * u)) for u in range(1, 301)]
    out = instrument.plateau_budget([_rec("happo", "a", 0, 0.5, curve), _rec("happo_cbf", "a", 0, 0.5, curve)])
    assert out["plateau_update"] == 120 and out["budget"] == 160   # 1.25 x 120 = 150 -> rounded up to 160
    # a curve still rising at the end never plateaus before its last window
    rising = [(u, u / 300) for u in range(1, 301)]
    assert instrument.plateau_budget([_rec("happo", "a", 0, 0.5, rising)])["budget"] == 300
    flat = [(u, 0.5) for u in range(1, 301)]
    assert instrument.plateau_budget([_rec("happo", "a", 0, 0.5, flat)])["budget"] == 100   # the floor


def test_power_table_uses_paired_pilot_spread(tmp_path, capsys):
    recs = []
    for k, (a, b) in enumerate([(1.0, 0.0), (1.0, 1.0), (0.5, 0.4), (0.9, 0.2)]):
        recs += [_rec("happo", "s", k, a, col=100.0), _rec("happo_cbf", "s", k, b, col=1.0)]
    rows = {r["claim"]: r for r in instrument.power_table(recs)}
    shield = rows["shield costs 8.0 pp SR"]
    assert shield["sd_from"].startswith("paired") and shield["effect_here"] == pytest.approx(-0.08)
    diffs = [-1.0, 0.0, -0.1, -0.7]
    import numpy as np
    assert shield["sd"] == pytest.approx(np.std(diffs, ddof=1))
    assert shield["runs_per_arm"] > 100
    col = rows["shield cuts Col./1k by 98.5%"]
    assert col["effect_here"] == pytest.approx(-98.5) and col["sd"] == 0.0 and col["runs_per_arm"] is None
    sage = rows["SAGE+CBF recovers 11.7 pp SR over HAPPO+CBF"]
    assert sage["sd_from"].startswith("sqrt(2)")   # no SAGE runs in a pilot: the reference arm's spread
    for r in recs:
        (tmp_path / f"{r['method']}__{r['scenario']}__seed{r['seed']}.json").write_text(json.dumps(r))
    assert main(["instrument", str(tmp_path)]) == 0
    assert "graded runs: 4 of 8" in capsys.readouterr().out
