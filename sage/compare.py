"""``sage compare LABEL=DIR ...``: one setting against others, measured the
same way. Each DIR is a ``sage suite --out`` directory (same methods,
scenarios and seeds, one ``--set`` apart, e.g. ``algo.split_k``); the table
gives, per variant and method (one row each: methods are never pooled), each deployment metric's mean over runs with a 95%
bootstrap CI over runs stratified by scenario (``sage.report.bootstrap_ci``),
the episode-pooled success rate with its Wilson interval, and how readable the
trees are: non-zero features per split, read from each run's checkpoint.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from common.algos.registry import ALL_METHODS
from common.audit.params import split_carriers
from sage.errors import UsageError
from sage.report import METHOD_TITLES, bootstrap_ci, load_results, run_value
from sage.runs import load_run

METRICS = (("success_rate", "SR", 100.0, "%"), ("margin_col_per_1k", "margin Col./1k", 1.0, ""),
           ("col_per_1k", "contact Col./1k", 1.0, ""), ("correction", "correction", 1.0, ""),
           ("intervention_rate", "QP intervenes", 100.0, "%"))


def wilson(successes: float, n: int, z: float = 1.96) -> list[float]:
    """Wilson score interval of a binomial proportion."""
    if n == 0:
        return [float("nan"), float("nan")]
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return [centre - half, centre + half]


def split_sparsity(run_dir: str | Path) -> float:
    """Mean non-zero weights per split vector over all carriers of a run's newest checkpoint."""
    _, params, _ = load_run(run_dir)
    return float(np.mean([(t.W != 0).sum(axis=1).mean() for t in split_carriers(params)]))


def variant_rows(label: str, out_dir: Path) -> list[dict]:
    """One row per method of the suite in ``out_dir`` (methods are never pooled: a
    suite of HAPPO and SAGE runs is two rows), in the registry's method order."""
    paths = sorted(out_dir.glob("*.json"))
    results = [r for r in load_results(p for p in paths if p.name != "suite_config.json")]
    if not results:
        raise UsageError(f"{label}={out_dir}: no run results (*.json from `sage suite --out`)")
    methods = [m for m in ALL_METHODS if any(r.method == m for r in results)]
    return [method_row(label, m, [r for r in results if r.method == m], out_dir) for m in methods]


def method_row(label: str, method: str, results: list, out_dir: Path) -> dict:
    """The row of one method's runs of a variant."""
    strata = [r.scenario for r in results]
    row = {"variant": label, "method": method, "runs": len(results), "scenarios": sorted(set(strata)),
           "overrides": sorted({o for r in results for o in r.budget.get("overrides", [])})}
    for key, *_ in METRICS:
        values = [run_value(r, key) for r in results]
        row[key] = float(np.nanmean([v for v in values if v is not None])) if values else float("nan")
        row[f"{key}_ci"] = bootstrap_ci(values, strata)
    wins = sum(r.eval["success_rate"] * r.eval["episodes"] for r in results)
    episodes = sum(int(r.eval["episodes"]) for r in results)
    row["episodes"], row["success_rate_wilson"] = episodes, wilson(wins, episodes)
    runs = [out_dir / "runs" / f"{r.method}__{r.scenario}__seed{r.seed}" for r in results]
    row["features_per_split"] = float(np.mean([split_sparsity(p) for p in runs if p.is_dir()] or [float("nan")]))
    row["per_scenario_sr"] = {s: float(np.mean([r.eval["success_rate"] for r in results if r.scenario == s]))
                              for s in sorted(set(strata))}
    return row


def _cell(row: dict, key: str, scale: float, unit: str) -> str:
    """``90.2% [80.5, 100.0]`` (percentages) or ``0.176 [0.0001, 0.352]``."""
    fmt = (lambda x: f"{scale * x:.1f}") if unit == "%" else (lambda x: f"{x:.3g}")
    lo, hi = row[f"{key}_ci"]
    return fmt(row[key]) + unit + ("" if math.isnan(lo) else f" [{fmt(lo)}, {fmt(hi)}]")


def markdown(rows: list[dict]) -> str:
    head = ["variant", "method", "runs", "features / split", *[m[1] for m in METRICS], "SR, pooled episodes (Wilson)"]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        lo, hi = row["success_rate_wilson"]
        out.append("| " + " | ".join([row["variant"], METHOD_TITLES[row["method"]], str(row["runs"]),
                                      f"{row['features_per_split']:.2f}",
                                      *[_cell(row, *m[0:1], *m[2:]) for m in METRICS],
                                      f"{100 * lo:.1f}–{100 * hi:.1f}% of {row['episodes']}"]) + " |")
    scen = sorted({s for r in rows for s in r["per_scenario_sr"]})
    out += ["", "| variant | method | " + " | ".join(f"SR {s}" for s in scen) + " |",
            "|---|---|" + "---|" * len(scen)]
    for row in rows:
        out.append(f"| {row['variant']} | {METHOD_TITLES[row['method']]} | " + " | ".join(
            f"{100 * row['per_scenario_sr'].get(s, float('nan')):.1f}%" for s in scen) + " |")
    return "\n".join(out)


def register(commands, _bench) -> None:
    p = commands.add_parser("compare", help="variants of one setting side by side (suite dirs), with CIs")
    p.add_argument("variants", nargs="+", metavar="LABEL=DIR", help="e.g. dense=results/sparse/k0")
    p.add_argument("--json", action="store_true", help="print JSON (default: Markdown)")
    p.set_defaults(func=cmd_compare)


def cmd_compare(args) -> int:
    rows = []
    for item in args.variants:
        label, sep, folder = item.partition("=")
        if not sep or not label or not Path(folder).is_dir():
            raise UsageError(f"{item!r}: expected LABEL=DIR with DIR a `sage suite --out` directory")
        try:
            rows += variant_rows(label, Path(folder))
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    print(json.dumps(rows, indent=1) if args.json else markdown(rows))
    return 0
