"""`sage instrument RESULTS`: can this instrument decide the paper's claims?

Reads a suite's result records (a pilot of HAPPO and HAPPO+CBF, per
docs/protocol/table1.toml's stopping rule) and prints:

- ``graded``: runs whose deployment SR lies strictly between 5% and 95% (a
  bimodal 0-or-1 per-run SR needs hundreds of runs per claim);
- ``budgets``: each scenario's budget by the protocol's stopping rule, applied to
  the pilot's training-success curves (the arms in the results: HAPPO and HAPPO+CBF);
- ``power``: for each claim of the abstract, the spread the pilot measured and the
  matched runs per arm that decide a difference of the paper's size at 95%
  (two-sided, power 0.8; ``sage.stats.runs_needed``).

Nothing here looks at SAIL, TALO or SAGE results: the spread of a claim about them
is taken from the pilot arms' own run-to-run spread (of a paired difference where
the pilot has one, else sqrt(2) x the between-run spread of the reference arm).
"""
from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from sage import stats
from sage.errors import UsageError, user_input

GRADED = (0.05, 0.95)

# The stopping rule of docs/protocol/table1.toml (fixed there before any result).
WINDOW, TOLERANCE, SCALE, ROUND_TO, MIN_BUDGET, MAX_BUDGET = 20, 0.05, 1.25, 20, 100, 300

# Claims of the abstract and Sec. IV with the paper's figures:
# (name, reference arm, arm, metric, paper's effect, kind) with kind "pp" (absolute
# difference of a rate) or "rel" (relative change of the reference's mean).
CLAIMS = [
    ("shield cuts Col./1k by 98.5%", "happo", "happo_cbf", "col_per_1k", -0.985, "rel"),
    ("shield costs 8.0 pp SR", "happo", "happo_cbf", "success_rate", -0.080, "pp"),
    ("SAGE+CBF recovers 11.7 pp SR over HAPPO+CBF", "happo_cbf", "sage", "success_rate", +0.117, "pp"),
    ("TALO+CBF recovers 7.6 pp SR over HAPPO+CBF", "happo_cbf", "talo_cbf", "success_rate", +0.076, "pp"),
    ("SAIL+CBF recovers 8.4 pp SR over HAPPO+CBF", "happo_cbf", "sail_cbf", "success_rate", +0.084, "pp"),
    ("SAGE+CBF cuts DR 37.4% -> 20.8%", "happo_cbf", "sage", "drop_rate", -0.166, "pp"),
    ("SAIL cuts proposal violation by 48.8%", "happo_cbf", "sail_cbf", "proposal_violation", -0.488, "rel"),
    ("SAIL cuts the correction by 85.2%", "happo_cbf", "sail_cbf", "correction", -0.852, "rel"),
]


def load_records(folder: str | Path) -> list[dict]:
    """The result records of a suite folder (``<run>.json``; suite_config.json skipped)."""
    out = []
    for path in sorted(Path(folder).glob("*.json")):
        if path.name in ("suite_config.json", "summary.json"):
            continue
        rec = json.loads(path.read_text())
        if not isinstance(rec, dict) or "eval" not in rec:
            raise ValueError(f"{path}: not a suite result record")
        out.append(rec)
    if not out:
        raise ValueError(f"{folder}: no result records")
    return out


def arm_of(rec: dict) -> str:
    return rec.get("arm") or rec["method"]


def graded_runs(records: list[dict]) -> dict:
    srs = [r["eval"].get("success_rate") for r in records]
    graded = [s for s in srs if s is not None and GRADED[0] < s < GRADED[1]]
    return {"graded": len(graded), "runs": len(srs), "per_run_sr": {
        f"{arm_of(r)}/{r['scenario']}/{r['seed']}": r["eval"].get("success_rate") for r in records}}


def _curve(rec: dict, key: str = "success_rate") -> tuple[np.ndarray, np.ndarray]:
    pts = [(p.get("update"), p.get(key)) for p in rec.get("train_curve", [])
           if p.get("update") is not None and p.get(key) is not None and np.isfinite(p.get(key))]
    if not pts:
        return np.zeros(0), np.zeros(0)
    u, v = zip(*pts)
    return np.asarray(u, float), np.asarray(v, float)


def plateau_budget(records: list[dict]) -> dict:
    """The protocol's stopping rule on one scenario's pilot runs: average the runs'
    training success in windows of WINDOW updates; the plateau is the first window after
    which no later window is more than TOLERANCE above it; the budget is SCALE x the
    plateau's end, rounded up to ROUND_TO, within [MIN_BUDGET, MAX_BUDGET]."""
    by_window: dict[int, list[float]] = defaultdict(list)
    last = 0
    for rec in records:
        u, v = _curve(rec)
        for w in np.unique((u - 1) // WINDOW).astype(int):
            by_window[w].append(float(np.mean(v[(u - 1) // WINDOW == w])))
        last = max(last, int(u.max()) if u.size else 0)
    windows = sorted(by_window)
    means = [float(np.mean(by_window[w])) for w in windows]
    plateau = None
    for i, m in enumerate(means):
        if all(later <= m + TOLERANCE for later in means[i + 1:]):
            plateau = (windows[i] + 1) * WINDOW
            break
    if plateau is None or not means:
        return {"budget": MAX_BUDGET, "plateau_update": None, "window_means": means, "trained": last}
    budget = int(math.ceil(SCALE * plateau / ROUND_TO) * ROUND_TO)
    return {"budget": min(MAX_BUDGET, max(MIN_BUDGET, budget)), "plateau_update": plateau,
            "window_means": [round(m, 4) for m in means], "trained": last}


def _pairs(records, ref, arm, metric) -> dict:
    by = {(arm_of(r), r["scenario"], r["seed"]): r["eval"].get(metric) for r in records}
    return {(s, k): (by[(arm, s, k)], by[(ref, s, k)]) for (a, s, k) in by
            if a == arm and (ref, s, k) in by}


def _spread(records, ref, arm, metric) -> tuple[float, str]:
    """SD of the paired difference arm - ref from the pilot, or a proxy from ``ref``'s spread."""
    pairs = _pairs(records, ref, arm, metric)
    if len(pairs) > 1:
        return stats.paired_difference_ci(pairs)["sd"], f"paired {arm} - {ref} over {len(pairs)} matched runs"
    vals = [r["eval"].get(metric) for r in records if arm_of(r) == ref and r["eval"].get(metric) is not None]
    if len(vals) > 1:
        return math.sqrt(2.0) * float(np.std(vals, ddof=1)), f"sqrt(2) x between-run SD of {ref} ({len(vals)} runs)"
    return float("nan"), "no spread measured"


def power_table(records: list[dict]) -> list[dict]:
    rows = []
    for name, ref, arm, metric, effect, kind in CLAIMS:
        sd, source = _spread(records, ref, arm, metric)
        ref_vals = [r["eval"].get(metric) for r in records if arm_of(r) == ref and r["eval"].get(metric) is not None]
        ref_mean = float(np.mean(ref_vals)) if ref_vals else float("nan")
        absolute = effect if kind == "pp" else effect * ref_mean
        rows.append({"claim": name, "metric": metric, "paper_effect": effect, "kind": kind,
                     "effect_here": absolute, "reference_mean": ref_mean, "sd": sd, "sd_from": source,
                     "runs_per_arm": stats.runs_needed(absolute, sd)})
    return rows


def observed_differences(records: list[dict], ref: str = "happo", arm: str = "happo_cbf") -> dict:
    """The pilot's own paired differences arm - ref (matched scenario and seed) with their
    stratified bootstrap CIs: the shield's effect the pilot itself measures."""
    out = {}
    for metric in ("success_rate", "drop_rate", "truncation_rate", "col_per_1k"):
        pairs = _pairs(records, ref, arm, metric)
        if pairs:
            d = stats.paired_difference_ci(pairs)
            out[metric] = {"difference": d["estimate"], "ci": d["ci"], "sd": d["sd"], "pairs": d["runs"]}
    return out


def analyze(folder: str | Path) -> dict:
    records = load_records(folder)
    scenarios = sorted({r["scenario"] for r in records})
    return {
        "results": str(folder), "arms": sorted({arm_of(r) for r in records}), "scenarios": scenarios,
        "graded": graded_runs(records),
        "budgets": {s: plateau_budget([r for r in records if r["scenario"] == s]) for s in scenarios},
        "power": power_table(records),
        "shield_effect": observed_differences(records),
        "outcomes": {arm: {k: float(np.mean([r["eval"].get(k) for r in records if arm_of(r) == arm
                                              and r["eval"].get(k) is not None] or [np.nan]))
                           for k in ("success_rate", "drop_rate", "truncation_rate", "col_per_1k")}
                     for arm in sorted({arm_of(r) for r in records})},
    }


def register(commands, bench) -> None:
    p = commands.add_parser("instrument", help="can a pilot's spread decide the paper's claims? graded runs, "
                                               "budgets by the protocol's stopping rule, runs needed per claim")
    p.add_argument("results", help="a suite's results folder (e.g. results/pilot)")
    p.add_argument("--json", action="store_true", help="print the analysis as JSON")
    p.set_defaults(func=_instrument)


def _instrument(args: argparse.Namespace) -> int:
    if not Path(args.results).is_dir():
        raise UsageError(f"{args.results}: not a results folder")
    with user_input(args.results):
        out = analyze(args.results)
    if args.json:
        print(json.dumps(out, indent=1, default=float))
        return 0
    g = out["graded"]
    print(f"graded runs: {g['graded']} of {g['runs']} (deployment SR strictly between 5% and 95%)")
    for s, b in out["budgets"].items():
        print(f"budget {s}: {b['budget']} updates (plateau at {b['plateau_update']}, trained {b['trained']})")
    for metric, d in out["shield_effect"].items():
        print(f"pilot HAPPO+CBF - HAPPO {metric}: {d['difference']:+.4g} [{d['ci'][0]:+.4g}, {d['ci'][1]:+.4g}] "
              f"over {d['pairs']} matched runs")
    for row in out["power"]:
        n = row["runs_per_arm"]
        print(f"{row['claim']}: effect {row['effect_here']:+.4g} {row['metric']}, sd {row['sd']:.3g} "
              f"({row['sd_from']}) -> {n if n is not None else 'n/a'} runs per arm")
    return 0
