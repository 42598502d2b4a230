"""Table I and the evaluation figures of Sec. IV from suite results.

A suite result is one JSON file per (method, scenario, seed) run, written by
`sage suite` (schema in ``RESULT_KEYS`` below). This module only reads those
files: every number in the table and the figures comes from a real run.

Aggregation follows the paper: per-scenario cells are the mean over seeds,
family rows are the mean of their scenarios, and the overall row is the mean
± standard deviation across runs (each run's deployment evaluation is one
sample).

Uncertainty: every cell that is a mean over runs carries a 95% percentile
bootstrap confidence interval of that mean (``bootstrap_ci``: 10,000 resamples
of the runs with replacement, a fresh ``numpy.random.default_rng(0)`` per cell,
so a cell's interval does not depend on which other cells are present; family
cells resample the seeds within each scenario, as the family mean is a mean of
scenario means). Each headline comparison of the paper's abstract also gets the
paired difference new − reference over the (scenario, seed) runs both methods
have, with its bootstrap CI over those pairs (``paired_difference``). An
interval needs at least two runs (two per scenario for a family cell; else it is
NaN and not printed). With the few seeds of a suite the percentile bootstrap
under-covers (its intervals are too narrow for n < ~10): read them as a lower
bound on the uncertainty, and prefer more seeds to a finer interval method.
"""
from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from common.algos.registry import ALL_METHODS, METHOD_SPECS
from common.env.scenarios import FAMILIES, SCENARIO_TITLES
from sage.errors import UsageError, user_input

METHOD_TITLES = {name: spec.title for name, spec in METHOD_SPECS.items()}
# Keys every result's "eval" block carries (deployment evaluation).
EVAL_KEYS = [
    "success_rate", "return_mean", "col_per_1k", "margin_col_per_1k", "drop_rate",
    "proposal_violation", "proposal_violation_any_wall", "correction",
    "tilt", "heading_error", "height_error", "completion_time",
]
RESULT_KEYS = ["method", "scenario", "seed", "eval", "train_curve", "budget"]
# report curve key <- learner metrics.jsonl key (episodes finished during that update)
CURVE_KEYS = {
    "episode_return": "ep_return_mean", "drop_rate": "ep_drop_mean", "success_rate": "ep_success_mean",
    "proposal_violation": "proposal_violation_rate", "correction": "correction_mean",
    "deploy_success_rate": "deploy_sr",   # the learner's periodic deterministic deployment probe
}


@dataclass
class Result:
    method: str
    scenario: str
    seed: int
    eval: dict
    train_curve: list
    budget: dict


def load_results(paths: Iterable[Path]) -> list[Result]:
    """Read result JSON files; a malformed file is an error that names it."""
    results = []
    for path in paths:
        path = Path(path)
        try:
            raw = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not valid JSON ({exc})") from exc
        except UnicodeDecodeError as exc:
            raise ValueError(f"{path}: not a text file ({exc.reason})") from exc
        if not isinstance(raw, dict):
            raise ValueError(f"{path}: a result is a JSON object, got {type(raw).__name__}")
        missing = [k for k in RESULT_KEYS if k not in raw]
        if missing:
            raise ValueError(f"{path}: result is missing keys {missing}")
        if raw["method"] not in METHOD_TITLES:
            raise ValueError(f"{path}: unknown method {raw['method']!r}")
        for key, kind in (("eval", dict), ("train_curve", list), ("budget", dict)):
            if not isinstance(raw[key], kind):
                raise ValueError(f"{path}: {key!r} must be a JSON {'object' if kind is dict else 'list'}")
        results.append(Result(**{k: raw[k] for k in RESULT_KEYS}))
    return results


def _mean(values: list[float]) -> float:
    values = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return float(np.mean(values)) if values else float("nan")


def _std(values: list[float]) -> float:
    values = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return float(np.std(values)) if len(values) > 1 else 0.0 if values else float("nan")


def cell(results: list[Result], method: str, scenario: str, key: str) -> float:
    return _mean([r.eval.get(key) for r in results if r.method == method and r.scenario == scenario])


# ----------------------------------------------------------------- bootstrap statistics
BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0
CI_LEVEL = 0.95


def _finite_pairs(values, strata):
    keep = [(float(v), g) for v, g in zip(values, strata)
            if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return [v for v, _ in keep], [g for _, g in keep]


def bootstrap_ci(values, strata=None, n_resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED,
                 level: float = CI_LEVEL) -> list[float]:
    """Percentile bootstrap CI ``[lo, hi]`` of the mean of ``values`` (None/NaN dropped).

    Each of ``n_resamples`` resamples draws len(values) values with replacement
    (``rng.integers(0, n)``, one row of indices per resample, rng =
    ``numpy.random.default_rng(seed)``) and takes their mean; the interval is the
    (1-level)/2 and (1+level)/2 percentiles (numpy's linear interpolation) of those
    means. With ``strata`` (one label per value) the statistic is the mean of the
    per-stratum means and each stratum is resampled within itself (strata in sorted
    label order). NaN unless every stratum has at least two values (a one-run stratum
    has no spread to resample, and its zero-width contribution would narrow the interval).
    """
    strata = [0] * len(values) if strata is None else list(strata)
    if len(strata) != len(values):
        raise ValueError("one stratum label per value")
    vals, labels = _finite_pairs(values, strata)
    groups = [np.asarray([v for v, g in zip(vals, labels) if g == lab]) for lab in sorted(set(labels))]
    if not groups or min(len(g) for g in groups) < 2:
        return [float("nan"), float("nan")]
    rng = np.random.default_rng(seed)
    stat = np.zeros(n_resamples)
    for g in groups:
        stat += g[rng.integers(0, len(g), size=(n_resamples, len(g)))].mean(axis=1)
    stat /= len(groups)
    tail = 50.0 * (1.0 - level)
    lo, hi = np.percentile(stat, [tail, 100.0 - tail])
    return [float(lo), float(hi)]


TRAIN_EXPOSURE_KEYS = ("train_col_per_1k", "train_margin_col_per_1k", "train_drop_rate", "train_env_steps")
CURVE_MEAN_KEYS = ("w_gap", "cos_ind_team")
# Like-for-like mechanism diagnostics, logged by every method (common/algos/diagnostics.py):
# their training means, reported in one table (docs/interfaces.md, learner metrics)
MECHANISM_KEYS = ("w_gap_first", "w_gap_mean", "cos_ind_team_first", "cos_ind_team_mean", "talo_condition_met",
                  "proposal_violation_rate", "correction_st", "exec_minus_prop", "sail_residual")
CURVE_MEAN_KEYS += MECHANISM_KEYS


def run_value(r: Result, key: str) -> float:
    """One run's value of a report key: its deployment eval, training exposure or curve mean."""
    if key in TRAIN_EXPOSURE_KEYS:
        return training_exposure(r)[key]
    if key in CURVE_MEAN_KEYS:
        return curve_mean(r, key)
    v = r.eval.get(key)
    return float("nan") if v is None else float(v)


def paired_difference(results: list[Result], ref: str, new: str, key: str, relative: bool = True,
                      n_resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED,
                      level: float = CI_LEVEL) -> dict:
    """``new`` − ``ref`` on ``key`` over the (scenario, seed) runs both methods have (a run
    repeated in the inputs counts once, as the mean of its copies; pairs with a NaN side are
    dropped): ``n`` pairs, matched means ``from``/``to``, mean difference ``diff`` with its
    percentile bootstrap ``ci`` over the pairs, and (``relative``) the relative reduction
    ``100 (1 - mean(new) / mean(ref))`` with its CI from the same resamples (None when the
    reference mean is 0 in the data or in some resample)."""
    def by_run(method):
        runs: dict = {}
        for r in results:
            if r.method == method:
                runs.setdefault((r.scenario, r.seed), []).append(run_value(r, key))
        return {k: _mean(v) for k, v in runs.items()}

    a_runs, b_runs = by_run(ref), by_run(new)
    keys = sorted(k for k in a_runs if k in b_runs and not (math.isnan(a_runs[k]) or math.isnan(b_runs[k])))
    nan = float("nan")
    out = {"n": len(keys), "from": nan, "to": nan, "diff": nan, "ci": [nan, nan]}
    if relative:
        out.update(reduction_pct=None, reduction_pct_ci=None)
    if not keys:
        return out
    a = np.array([a_runs[k] for k in keys])
    b = np.array([b_runs[k] for k in keys])
    out.update({"from": float(a.mean()), "to": float(b.mean()), "diff": float((b - a).mean())})
    if relative and a.mean() > 0:
        out["reduction_pct"] = float(100.0 * (1.0 - b.mean() / a.mean()))
    if len(keys) < 2:
        return out
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(keys), size=(n_resamples, len(keys)))
    tail = 50.0 * (1.0 - level)
    q = [tail, 100.0 - tail]
    out["ci"] = [float(x) for x in np.percentile((b - a)[idx].mean(axis=1), q)]
    ra, rb = a[idx].mean(axis=1), b[idx].mean(axis=1)
    if out.get("reduction_pct") is not None and np.all(ra > 0):
        out["reduction_pct_ci"] = [float(x) for x in np.percentile(100.0 * (1.0 - rb / ra), q)]
    return out


def training_exposure(r: Result) -> dict:
    """Collision steps per 1000 env steps and drop rate over the whole training
    run, from the learner's per-update episode metrics (what the robots went
    through while learning, as opposed to the deployment evaluation)."""
    rows = [p for p in r.train_curve if "episodes" in p]
    eps = sum(p.get("episodes", 0) for p in rows)
    steps = max((p.get("env_steps", 0) for p in rows), default=0)
    col = sum(p.get("ep_collision_steps_mean", 0.0) * p.get("episodes", 0) for p in rows)
    drops = sum(p.get("ep_drop_mean", 0.0) * p.get("episodes", 0) for p in rows)
    nan = float("nan")
    # margin violations: the learner's per-update rate over the episodes that ended in it
    margin = [(p["margin_col_per_1k"], p.get("episodes", 0)) for p in rows if p.get("margin_col_per_1k") is not None]
    weight = sum(w for _, w in margin)
    return {"train_col_per_1k": 1000.0 * col / steps if steps else nan,
            "train_margin_col_per_1k": sum(v * w for v, w in margin) / weight if weight else nan,
            "train_drop_rate": drops / eps if eps else nan, "train_env_steps": steps}


def summarize(results: list[Result]) -> dict:
    """Nested summary: per scenario, per family, overall, for each method present."""
    methods = [m for m in ALL_METHODS if any(r.method == m for r in results)]
    scenarios = [s for fam in FAMILIES.values() for s in fam if any(r.scenario == s for r in results)]
    out: dict = {"methods": methods, "scenarios": {}, "families": {}, "overall": {}}
    for s in scenarios:
        out["scenarios"][s] = {}
        for m in methods:
            runs = [r for r in results if r.method == m and r.scenario == s]
            row = {k: cell(results, m, s, k) for k in EVAL_KEYS}
            row["ci"] = {k: bootstrap_ci([r.eval.get(k) for r in runs]) for k in EVAL_KEYS}
            out["scenarios"][s][m] = row
    for fam, members in FAMILIES.items():
        present = [s for s in members if s in out["scenarios"]]
        if not present:
            continue
        out["families"][fam] = {}
        for m in methods:
            runs = [r for r in results if r.method == m and r.scenario in present]
            row = {k: _mean([out["scenarios"][s][m][k] for s in present]) for k in EVAL_KEYS}
            # the family mean is a mean of scenario means: resample seeds within each scenario
            row["ci"] = {k: bootstrap_ci([r.eval.get(k) for r in runs], strata=[r.scenario for r in runs])
                         for k in EVAL_KEYS}
            out["families"][fam][m] = row
    for m in methods:
        runs = [r for r in results if r.method == m]
        out["overall"][m] = {}
        for k in EVAL_KEYS + list(TRAIN_EXPOSURE_KEYS) + list(CURVE_MEAN_KEYS):
            vals = [run_value(r, k) for r in runs]
            out["overall"][m][k] = {"mean": _mean(vals), "std": _std(vals), "ci": bootstrap_ci(vals)}
        out["overall"][m]["runs"] = len(runs)
    out["train_scenarios"] = {}
    for s in scenarios:
        out["train_scenarios"][s] = {}
        for m in methods:
            vals = [training_exposure(r)["train_col_per_1k"] for r in results if r.method == m and r.scenario == s]
            out["train_scenarios"][s][m] = {"train_col_per_1k": _mean(vals), "ci": bootstrap_ci(vals)}
    out["bootstrap"] = {"method": "percentile", "level": CI_LEVEL, "resamples": BOOTSTRAP_RESAMPLES,
                        "seed": BOOTSTRAP_SEED, "unit": "runs (pairs matched on (scenario, seed) for differences)"}
    out["headline"] = headline(out, results)
    return out


def curve_mean(r: Result, key: str) -> float:
    """Mean of a per-update diagnostic over the whole training run (NaN if never logged)."""
    return _mean([p.get(key) for p in r.train_curve])


def _change(ref: float, new: float) -> dict:
    """ref -> new with the relative reduction in % (None when the reference is 0 or missing)."""
    ok = not (math.isnan(ref) or math.isnan(new))
    red = 100.0 * (1.0 - new / ref) if ok and ref > 0 else None
    return {"from": ref, "to": new, "reduction_pct": red}


def headline(summary: dict, results: list[Result] | None = None) -> dict:
    """The comparisons the paper's abstract and Sec. IV quote, from this suite's overall rows:
    the shield's collision reduction and SR cost (HAPPO -> HAPPO+CBF), SAGE's SR recovery and
    DR change (HAPPO+CBF -> SAGE+CBF), SAIL's proposal-violation and correction reduction
    (HAPPO+CBF -> SAIL+CBF) and TALO's W_gap reduction (SAIL+CBF -> SAGE+CBF, same
    tree-SAIL proposal graph; training means); plus SAGE+CBF's overall SR and Col./1k with
    their CIs. With ``results`` every comparison also carries ``paired``: the paired
    difference over matched (scenario, seed) runs with its bootstrap CI
    (``paired_difference``)."""
    o = summary["overall"]

    def get(m, k):
        return o[m][k]["mean"]

    def comp(ref, new, key, change=True):
        c = _change(get(ref, key), get(new, key)) if change else {"from": get(ref, key), "to": get(new, key)}
        if results is not None:
            c["paired"] = paired_difference(results, ref, new, key, relative=change)
        return c

    out = {}
    if "sage" in o:
        out["sage_overall"] = {k: {"mean": o["sage"][k]["mean"], "ci": o["sage"][k]["ci"], "runs": o["sage"]["runs"]}
                               for k in ("success_rate", "col_per_1k")}
    if "happo" in o and "happo_cbf" in o:
        out["shield"] = {
            "col_per_1k": comp("happo", "happo_cbf", "col_per_1k"),
            "train_col_per_1k": comp("happo", "happo_cbf", "train_col_per_1k"),
            "success_rate": comp("happo", "happo_cbf", "success_rate", change=False),
        }
    if "happo_cbf" in o and "sage" in o:
        out["sage_vs_shield"] = {
            "success_rate": comp("happo_cbf", "sage", "success_rate", change=False),
            "drop_rate": comp("happo_cbf", "sage", "drop_rate", change=False),
        }
    if "happo_cbf" in o and "sail_cbf" in o:
        out["sail"] = {k: comp("happo_cbf", "sail_cbf", k) for k in ("proposal_violation", "correction")}
    if "sail_cbf" in o and "sage" in o:
        out["talo"] = {"w_gap": comp("sail_cbf", "sage", "w_gap"),
                       "cos_ind_team": comp("sail_cbf", "sage", "cos_ind_team", change=False)}
    return out


def headline_markdown(h: dict) -> list[str]:
    def red(c):
        pct = c["reduction_pct"]
        if pct is None:
            return "no reduction to state: the reference is 0"
        return f"{pct:.1f}% lower" if pct >= 0 else f"{-pct:.1f}% higher"

    def arrow(c, digits=1, scale=1.0, unit=""):   # "from → to" of one comparison
        return f"{_fmt(c['from'], digits, scale)}{unit} → {_fmt(c['to'], digits, scale)}{unit}"

    def paired(name, c, digits=1, scale=1.0, unit=""):   # "name Δ d [lo, hi]" of the matched runs
        p = c.get("paired")
        if not p or not p["n"]:
            return f"{name}: no matched runs"
        d = p["diff"] * scale
        text = f"{name} Δ {'–' if math.isnan(d) else f'{d:+.{digits}f}'}{unit}{_ci(p['ci'], digits, scale)}"
        if p.get("reduction_pct_ci"):
            lo, hi = p["reduction_pct_ci"]
            text += f" (reduction {p['reduction_pct']:.1f}% [{lo:.1f}, {hi:.1f}])"
        return text

    def pairs(items):   # sub-bullet: the paired differences of one headline entry
        ns = {c["paired"]["n"] for _, c, *_ in items if "paired" in c}
        if not ns:
            return []
        n = "/".join(str(x) for x in sorted(ns))
        return [f"  - paired over {n} matched (scenario, seed) runs, new − reference [95% bootstrap CI]: "
                + "; ".join(paired(*item) for item in items) + "."]

    lines = []
    if "sage_overall" in h:
        so = h["sage_overall"]
        lines.append(f"- SAGE+CBF overall ({so['success_rate']['runs']} runs): SR "
                     f"{_fmt(so['success_rate']['mean'], 1, 100)}%{_ci(so['success_rate']['ci'], 1, 100)}; "
                     f"Col./1k {_fmt(so['col_per_1k']['mean'], 2)}{_ci(so['col_per_1k']['ci'], 2)}.")
    if "shield" in h:
        sh = h["shield"]
        lines.append(f"- Exact CBF filtering (HAPPO → HAPPO+CBF): deployment Col./1k {arrow(sh['col_per_1k'], 2)} "
                     f"({red(sh['col_per_1k'])}); during training {arrow(sh['train_col_per_1k'], 2)} "
                     f"({red(sh['train_col_per_1k'])}); SR {arrow(sh['success_rate'], scale=100, unit='%')}.")
        lines += pairs([("Col./1k", sh["col_per_1k"], 2), ("training Col./1k", sh["train_col_per_1k"], 2),
                            ("SR", sh["success_rate"], 1, 100, " pp")])
    if "sage_vs_shield" in h:
        sv = h["sage_vs_shield"]
        gain = (sv["success_rate"]["to"] - sv["success_rate"]["from"]) * 100
        lines.append(f"- SAGE+CBF vs HAPPO+CBF: SR {arrow(sv['success_rate'], scale=100, unit='%')} ({gain:+.1f} pp); "
                     f"DR {arrow(sv['drop_rate'], scale=100, unit='%')}.")
        lines += pairs([("SR", sv["success_rate"], 1, 100, " pp"), ("DR", sv["drop_rate"], 1, 100, " pp")])
    if "sail" in h:
        sa = h["sail"]
        lines.append(f"- SAIL (HAPPO+CBF → SAIL+CBF): proposal violation "
                     f"{arrow(sa['proposal_violation'], scale=100, unit='%')} ({red(sa['proposal_violation'])}); "
                     f"correction {arrow(sa['correction'], 3)} ({red(sa['correction'])}).")
        lines += pairs([("proposal violation", sa["proposal_violation"], 1, 100, " pp"),
                            ("correction", sa["correction"], 3)])
    if "talo" in h:
        ta = h["talo"]
        lines.append(f"- TALO (SAIL+CBF → SAGE+CBF, training means): W_gap {arrow(ta['w_gap'], 3)} "
                     f"({red(ta['w_gap'])}); cos(g_ind, g_team) {arrow(ta['cos_ind_team'], 3)}.")
        lines += pairs([("W_gap", ta["w_gap"], 3), ("cos(g_ind, g_team)", ta["cos_ind_team"], 3)])
    return lines


def _fmt(x: float, digits: int = 1, scale: float = 1.0) -> str:
    return "–" if x is None or math.isnan(x) else f"{x * scale:.{digits}f}"


def _ci(ci, digits: int = 1, scale: float = 1.0) -> str:
    """' [lo, hi]' of a bootstrap CI, or '' when there is none (fewer than two runs)."""
    if not ci or any(x is None or math.isnan(x) for x in ci):
        return ""
    return f" [{_fmt(ci[0], digits, scale)}, {_fmt(ci[1], digits, scale)}]"


def table_markdown(summary: dict) -> str:
    """Table I as Markdown: SR (%) and Col./1k per scenario, family means, overall row."""
    methods = summary["methods"]
    head = "| Family | Scenario | " + " | ".join(
        f"{METHOD_TITLES[m]} SR | {METHOD_TITLES[m]} Col./1k" for m in methods) + " |"
    sep = "|" + "---|" * (2 + 2 * len(methods))
    lines = ["### Per scenario (SR in %, Col./1k in collision steps per 1000 env steps; mean over seeds "
             "[95% bootstrap CI], family rows: mean of the scenario means)", "", head, sep]

    def sr_col(cell, bold=""):
        ci = cell.get("ci", {})
        return (f"{bold}{_fmt(cell['success_rate'], scale=100)}{bold}{_ci(ci.get('success_rate'), 1, 100)} | "
                f"{bold}{_fmt(cell['col_per_1k'])}{bold}{_ci(ci.get('col_per_1k'))}")

    for fam, members in FAMILIES.items():
        for s in members:
            if s not in summary["scenarios"]:
                continue
            row = summary["scenarios"][s]
            lines.append(f"| {fam} | {SCENARIO_TITLES[s]} | " + " | ".join(sr_col(row[m]) for m in methods) + " |")
        if fam in summary["families"]:
            row = summary["families"][fam]
            lines.append(f"| {fam} | **{fam} mean** | " + " | ".join(sr_col(row[m], "**") for m in methods) + " |")
    lines += ["", "### Overall (mean ± std across runs [95% bootstrap CI of the mean])", "",
              "| Method | Runs | SR (%) | Return | Col./1k (contact) | Col./1k (margin) | DR (%) | Proposal viol. (%) "
              "| of which wall rows (%) | Correction |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for m in methods:
        o = summary["overall"][m]

        def pm(key, scale=1.0, digits=1):
            return (f"{_fmt(o[key]['mean'], digits, scale)} ± {_fmt(o[key]['std'], digits, scale)}"
                    f"{_ci(o[key].get('ci'), digits, scale)}")
        viol = pm("proposal_violation", 100) if METHOD_SPECS[m].shielded else "N/A"
        wall_viol = pm("proposal_violation_any_wall", 100) if METHOD_SPECS[m].shielded else "N/A"
        corr = pm("correction", 1, 3) if METHOD_SPECS[m].shielded else "N/A"
        lines.append(f"| {METHOD_TITLES[m]} | {o['runs']} | {pm('success_rate', 100)} | {pm('return_mean', 1, 2)} | "
                     f"{pm('col_per_1k')} | {pm('margin_col_per_1k')} | {pm('drop_rate', 100)} | {viol} | {wall_viol} "
                     f"| {corr} |")
    if summary.get("headline"):
        lines += ["", "### Headline comparisons (the quantities of the paper's abstract, from the rows above)", ""]
        lines += headline_markdown(summary["headline"])
        b = summary.get("bootstrap")
        if b:
            lines += ["", f"CIs: {100 * b['level']:.0f}% {b['method']} bootstrap, {b['resamples']:,} resamples of the "
                          f"runs (of the matched (scenario, seed) pairs for a Δ), seed {b['seed']}; none with fewer "
                          "than two runs (per scenario, for a family mean)."]
    if summary.get("train_scenarios"):
        lines += ["", "### Col./1k during training, per scenario (same budget)", "",
                  "| Scenario | " + " | ".join(METHOD_TITLES[m] for m in methods) + " |",
                  "|" + "---|" * (1 + len(methods))]
        for s, row in summary["train_scenarios"].items():
            lines.append(f"| {SCENARIO_TITLES[s]} | " + " | ".join(
                _fmt(row[m]["train_col_per_1k"], 2) + _ci(row[m].get("ci"), 2) for m in methods) + " |")
    lines += ["", "### During training (same budget; collision steps and drops the carriers went through while learning)", "",
              "| Method | Env steps | Col./1k (contact) | Col./1k (margin) | DR (%) |", "|---|---|---|---|---|"]
    for m in methods:
        o = summary["overall"][m]
        lines.append(f"| {METHOD_TITLES[m]} | {_fmt(o['train_env_steps']['mean'], 0)} | "
                     f"{_fmt(o['train_col_per_1k']['mean'], 2)} ± {_fmt(o['train_col_per_1k']['std'], 2)}"
                     f"{_ci(o['train_col_per_1k'].get('ci'), 2)} | "
                     f"{_fmt(o['train_margin_col_per_1k']['mean'], 2)} ± {_fmt(o['train_margin_col_per_1k']['std'], 2)} | "
                     f"{_fmt(o['train_drop_rate']['mean'], 1, 100)} ± {_fmt(o['train_drop_rate']['std'], 1, 100)}"
                     f"{_ci(o['train_drop_rate'].get('ci'), 1, 100)} |")
    present = [k for k in MECHANISM_KEYS if any(not math.isnan(summary["overall"][m][k]["mean"]) for m in methods)]
    if present:
        lines += ["", "### Mechanism diagnostics during training (mean over updates, then mean ± std across runs)",
                  "", "W_gap and cos(g_ind, g_team) at the first minibatch of each update before any step (`_first`)"
                  " and over all minibatches (`_mean`), the same points for every method; `talo_condition_met`: share"
                  " of applied TALO steps meeting Eq. talo_condition; proposal violation and ||Q(a_ST) - a_ST||"
                  " (`correction_st`) of the training batches; margin Col./1k: training steps per 1,000 with a"
                  " barrier of the shield's own specification (a carrier disc or payload point within its safety"
                  " margin of a wall) below 0.", "",
                  "| Method | " + " | ".join(present) + " |", "|" + "---|" * (1 + len(present))]
        for m in methods:
            o = summary["overall"][m]
            lines.append(f"| {METHOD_TITLES[m]} | " + " | ".join(
                f"{_fmt(o[k]['mean'], 3)} ± {_fmt(o[k]['std'], 3)}" for k in present) + " |")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- figures

def _curves(results: list[Result], method: str, key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and std of a training-curve key over runs, on the shared progress grid [0, 1]."""
    grid = np.linspace(0.0, 1.0, 41)
    ys = []
    for r in results:
        if r.method != method or not r.train_curve:
            continue
        pts = [(p.get("progress"), p.get(key, p.get(CURVE_KEYS.get(key, key)))) for p in r.train_curve]
        pts = [(x, y) for x, y in pts if x is not None and y is not None and np.isfinite(y)]
        if len(pts) < 2:
            continue
        x, y = map(np.asarray, zip(*pts))
        ys.append(np.interp(grid, x, y))
    if not ys:
        return grid, np.full_like(grid, np.nan), np.full_like(grid, np.nan)
    ys = np.stack(ys)
    return grid, ys.mean(0), ys.std(0)


# Fig. payload_panels: (eval key, title, y-axis label with its unit; common/env/batch_env.py's episode metrics)
PAYLOAD_PANELS = [("tilt", "(a) payload tilt", "mean tilt per step (deg)"),
                  ("heading_error", "(b) heading error", "mean |route tangent − yaw| (rad)"),
                  ("height_error", "(c) height error", "mean |height − carry height| (m)"),
                  ("completion_time", "(d) completion time", "time to goal, successes (s)")]


def probe_points(results: list[Result], method: str) -> list[tuple[float, float]]:
    """(progress, deployment-probe SR) of every finite probe the method's runs logged."""
    out = []
    for r in results:
        if r.method != method:
            continue
        for p in r.train_curve:
            x, y = p.get("progress"), p.get("deploy_success_rate", p.get("deploy_sr"))
            if x is not None and y is not None and np.isfinite(y):
                out.append((float(x), float(y)))
    return out


def write_figures(results: list[Result], summary: dict, out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    methods = summary["methods"]
    colors = dict(zip(ALL_METHODS, ["#7f7f7f", "#1f77b4", "#2ca02c", "#ff7f0e", "#d62728", "#9467bd"]))
    written = []

    # Fig. main_sr: family-level SR (top) and Col./1k at deployment (middle) and during training
    # (bottom). A symlog axis (linear below 1) stands in for the paper's broken axis and keeps
    # an exact 0 at 0 instead of a log-scale floor.
    fams = list(summary["families"])
    if fams:
        fig, (ax_sr, ax_col, ax_tr) = plt.subplots(3, 1, figsize=(7, 8), sharex=True)
        width = 0.8 / max(len(methods), 1)
        for j, m in enumerate(methods):
            xs = np.arange(len(fams)) + (j - (len(methods) - 1) / 2) * width
            bars = {"sr": [], "sr_err": [], "col": [], "col_err": [], "tr": [], "tr_err": []}
            for fam in fams:
                runs = [r for r in results if r.method == m and r.scenario in FAMILIES[fam]]
                sr = [r.eval.get("success_rate") for r in runs]
                bars["sr"].append(100 * _mean(sr)); bars["sr_err"].append(100 * _std(sr))
                col = [r.eval.get("col_per_1k") for r in runs]
                bars["col"].append(_mean(col)); bars["col_err"].append(_std(col))
                tr = [training_exposure(r)["train_col_per_1k"] for r in runs]
                bars["tr"].append(_mean(tr)); bars["tr_err"].append(_std(tr))
            ax_sr.bar(xs, bars["sr"], width, yerr=bars["sr_err"], color=colors[m], label=METHOD_TITLES[m], capsize=2)
            for ax, key in ((ax_col, "col"), (ax_tr, "tr")):
                ax.bar(xs, bars[key], width, yerr=bars[key + "_err"], color=colors[m], capsize=2)
                for x, v in zip(xs, bars[key]):   # print the value: a 0 bar is otherwise invisible
                    ax.text(x, v if np.isfinite(v) else 0, _fmt(v), ha="center", va="bottom", fontsize=6)
        ax_sr.set_ylabel("SR (%) ↑"); ax_sr.set_ylim(0, 105)
        ax_sr.legend(fontsize=7, ncol=len(methods), loc="lower center", bbox_to_anchor=(0.5, 1.0))
        for ax, label in ((ax_col, "deployment Col./1k ↓"), (ax_tr, "training Col./1k ↓")):
            top = max([b.get_height() for b in ax.patches if np.isfinite(b.get_height())], default=0.0)
            ax.set_yscale("symlog", linthresh=1.0); ax.set_ylim(0, max(2.0 * top, 1.0)); ax.set_ylabel(label)
        ax_tr.set_xticks(np.arange(len(fams))); ax_tr.set_xticklabels(fams)
        fig.tight_layout(); path = out_dir / "main_sr.png"; fig.savefig(path, dpi=130); plt.close(fig)
        written.append(path)

    # Fig. reward_drop: training curves of return and drop rate, plus (where the learner
    # logged it) the deterministic deployment probe, which can differ from training SR.
    panels = [("episode_return", "(a) episode return", "team return per episode"),
              ("drop_rate", "(b) drop rate", "share of episodes dropped")]
    if any(probe_points(results, m) for m in methods):
        panels.append(("deploy_success_rate", "(c) deployment SR (probe: trees + exact QP)",
                       "probe success rate"))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.4))
    for (key, title, ylabel), ax in zip(panels, axes):
        for m in methods:
            g, mu, sd = _curves(results, m, key)
            lo, hi = (mu - sd, mu + sd) if key == "episode_return" else (np.clip(mu - sd, 0, 1), np.clip(mu + sd, 0, 1))
            ax.plot(g, mu, color=colors[m], label=METHOD_TITLES[m]); ax.fill_between(g, lo, hi, color=colors[m], alpha=0.15)
            pts = probe_points(results, m) if key == "deploy_success_rate" else []
            if pts and not np.isfinite(mu).any():
                # the probe runs every deploy_probe_every updates: runs too short for two
                # probes have no curve, so their probes are drawn as points
                x, y = zip(*pts)
                ax.plot(x, y, "o", ms=4, color=colors[m], alpha=0.7)
        ax.set_title(title, fontsize=9); ax.set_xlabel("training progress (share of the budget)")
        ax.set_ylabel(ylabel, fontsize=8); ax.set_xlim(-0.02, 1.02)
        if key != "episode_return":
            ax.set_ylim(-0.03, 1.03)
    axes[0].legend(fontsize=7)
    fig.tight_layout(); path = out_dir / "reward_drop.png"; fig.savefig(path, dpi=130); plt.close(fig)
    written.append(path)

    # Fig. sail_talo_ablation: mechanism panels (a)-(d).
    panels = [("proposal_violation", "(a) proposal violation", "share of steps with a row violated"),
              ("correction", "(b) proposal–execution correction", "mean ‖a_exec − a_prop‖"),
              ("w_gap", "(c) $W_{gap}$", "$W_{gap}$ (Eq. talo_gap)"),
              ("cos_ind_team", "(d) cos($g_{ind}$, $g_{team}$)", "cosine")]
    fig, axes = plt.subplots(2, 2, figsize=(9, 6))
    for ax, (key, title, ylabel) in zip(axes.flat, panels):
        for m in methods:
            if not METHOD_SPECS[m].shielded:
                continue
            g, mu, sd = _curves(results, m, key)
            ax.plot(g, mu, color=colors[m], label=METHOD_TITLES[m]); ax.fill_between(g, mu - sd, mu + sd, color=colors[m], alpha=0.15)
        ax.set_title(title, fontsize=9); ax.set_xlabel("training progress (share of the budget)")
        ax.set_ylabel(ylabel, fontsize=8)
    if axes[0, 0].get_legend_handles_labels()[0]:
        axes[0, 0].legend(fontsize=7)
    fig.tight_layout(); path = out_dir / "sail_talo_ablation.png"; fig.savefig(path, dpi=130); plt.close(fig)
    written.append(path)

    # Fig. payload_panels: execution-level quality per method.
    fig, axes = plt.subplots(1, 4, figsize=(12, 3.6))
    for ax, (key, title, unit) in zip(axes, PAYLOAD_PANELS):
        mus = [summary["overall"][m][key]["mean"] for m in methods]
        sds = [summary["overall"][m][key]["std"] for m in methods]
        bars = ax.bar(range(len(methods)), mus, yerr=sds, color=[colors[m] for m in methods], capsize=2)
        for b, m in zip(bars, methods):
            b.set_label(METHOD_TITLES[m])
        ax.set_xticks(range(len(methods))); ax.set_xticklabels([METHOD_TITLES[m] for m in methods], rotation=45, fontsize=7)
        ax.set_title(title, fontsize=9); ax.set_ylabel(unit, fontsize=8)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="upper center", ncol=len(methods), fontsize=7,
               title="deployment evaluation, mean ± std across runs (lower is better)", title_fontsize=7)
    fig.tight_layout(rect=(0, 0, 1, 0.86)); path = out_dir / "payload_panels.png"; fig.savefig(path, dpi=130)
    plt.close(fig)
    written.append(path)
    return written


def write_report(result_paths: Iterable[Path], out_dir: Path) -> dict:
    return report_results(load_results(result_paths), out_dir)


def report_results(results: list[Result], out_dir: Path) -> dict:
    if not results:
        raise ValueError("no results to report")
    summary = summarize(results)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "table1.md").write_text(table_markdown(summary))
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=True))
    figures = write_figures(results, summary, out_dir)
    return {"table": str(out_dir / "table1.md"), "summary": str(out_dir / "summary.json"),
            "figures": [str(p) for p in figures], "runs": len(results)}


# ----------------------------------------------------------------- command line
def register(commands, bench) -> None:
    p = commands.add_parser("report", help="Table I (Markdown) and the paper's figures from suite results")
    p.add_argument("results", nargs="+", help="result JSON files or directories holding them")
    p.add_argument("--out", default="results/report")
    p.set_defaults(func=_report)


def _report(args: argparse.Namespace) -> int:
    paths = []
    for item in args.results:
        p = Path(item)
        if not p.exists():
            raise UsageError(f"no such result file or directory: {p}")
        paths += sorted(p.glob("*.json")) if p.is_dir() else [p]
    paths = [p for p in paths if p.name not in ("suite_config.json", "summary.json")]
    if not paths:
        raise UsageError(f"no result JSON files in {' '.join(args.results)}")
    with user_input():
        results = load_results(paths)
    out_dir = Path(args.out)
    if out_dir.exists() and not out_dir.is_dir():
        raise UsageError(f"--out {out_dir} exists and is not a directory")
    out = report_results(results, out_dir)
    print(Path(out["table"]).read_text())
    print(json.dumps(out, indent=2))
    return 0
