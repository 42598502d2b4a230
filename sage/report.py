"""Table I and the evaluation figures of Sec. IV from suite results.

A suite result is one JSON file per (method, scenario, seed) run, written by
`sage suite` (schema in ``RESULT_KEYS`` below). This module only reads those
files: every number in the table and the figures comes from a real run.

Aggregation follows the paper: per-scenario cells are the mean over seeds,
family rows are the mean of their scenarios, and the overall row is the mean
± standard deviation across runs (each run's deployment evaluation is one
sample).
"""
from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from common.algos.registry import METHOD_SPECS, METHODS
from common.env.scenarios import FAMILIES, SCENARIO_TITLES
from sage.errors import UsageError, user_input

METHOD_TITLES = {name: spec.title for name, spec in METHOD_SPECS.items()}
# Keys every result's "eval" block carries (deployment evaluation).
EVAL_KEYS = [
    "success_rate", "return_mean", "col_per_1k", "drop_rate",
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
    return {"train_col_per_1k": 1000.0 * col / steps if steps else nan,
            "train_drop_rate": drops / eps if eps else nan, "train_env_steps": steps}


def summarize(results: list[Result]) -> dict:
    """Nested summary: per scenario, per family, overall, for each method present."""
    methods = [m for m in METHODS if any(r.method == m for r in results)]
    scenarios = [s for fam in FAMILIES.values() for s in fam if any(r.scenario == s for r in results)]
    out: dict = {"methods": methods, "scenarios": {}, "families": {}, "overall": {}}
    for s in scenarios:
        out["scenarios"][s] = {
            m: {k: cell(results, m, s, k) for k in EVAL_KEYS} for m in methods
        }
    for fam, members in FAMILIES.items():
        present = [s for s in members if s in out["scenarios"]]
        if not present:
            continue
        out["families"][fam] = {
            m: {k: _mean([out["scenarios"][s][m][k] for s in present]) for k in EVAL_KEYS}
            for m in methods
        }
    for m in methods:
        runs = [r for r in results if r.method == m]
        out["overall"][m] = {
            k: {"mean": _mean([r.eval.get(k) for r in runs]), "std": _std([r.eval.get(k) for r in runs])}
            for k in EVAL_KEYS
        }
        out["overall"][m]["runs"] = len(runs)
        exposure = [training_exposure(r) for r in runs]
        for k in ("train_col_per_1k", "train_drop_rate", "train_env_steps"):
            out["overall"][m][k] = {"mean": _mean([e[k] for e in exposure]), "std": _std([e[k] for e in exposure])}
        for k in ("w_gap", "cos_ind_team"):
            out["overall"][m][k] = {"mean": _mean([curve_mean(r, k) for r in runs]),
                                    "std": _std([curve_mean(r, k) for r in runs])}
    out["train_scenarios"] = {
        s: {m: {"train_col_per_1k": _mean([training_exposure(r)["train_col_per_1k"] for r in results
                                           if r.method == m and r.scenario == s])} for m in methods}
        for s in scenarios
    }
    out["headline"] = headline(out)
    return out


def curve_mean(r: Result, key: str) -> float:
    """Mean of a per-update diagnostic over the whole training run (NaN if never logged)."""
    return _mean([p.get(key) for p in r.train_curve])


def _change(ref: float, new: float) -> dict:
    """ref -> new with the relative reduction in % (None when the reference is 0 or missing)."""
    ok = not (math.isnan(ref) or math.isnan(new))
    red = 100.0 * (1.0 - new / ref) if ok and ref > 0 else None
    return {"from": ref, "to": new, "reduction_pct": red}


def headline(summary: dict) -> dict:
    """The comparisons the paper's abstract and Sec. IV quote, from this suite's overall rows:
    the shield's collision reduction and SR cost (HAPPO -> HAPPO+CBF), SAGE's SR recovery and
    DR change (HAPPO+CBF -> SAGE+CBF), SAIL's proposal-violation and correction reduction
    (HAPPO+CBF -> SAIL+CBF) and TALO's W_gap reduction (SAIL+CBF -> SAGE+CBF, same
    tree-SAIL proposal graph; training means)."""
    o = summary["overall"]

    def get(m, k):
        return o[m][k]["mean"]

    out = {}
    if "happo" in o and "happo_cbf" in o:
        out["shield"] = {
            "col_per_1k": _change(get("happo", "col_per_1k"), get("happo_cbf", "col_per_1k")),
            "train_col_per_1k": _change(get("happo", "train_col_per_1k"), get("happo_cbf", "train_col_per_1k")),
            "success_rate": {"from": get("happo", "success_rate"), "to": get("happo_cbf", "success_rate")},
        }
    if "happo_cbf" in o and "sage" in o:
        out["sage_vs_shield"] = {
            "success_rate": {"from": get("happo_cbf", "success_rate"), "to": get("sage", "success_rate")},
            "drop_rate": {"from": get("happo_cbf", "drop_rate"), "to": get("sage", "drop_rate")},
        }
    if "happo_cbf" in o and "sail_cbf" in o:
        out["sail"] = {k: _change(get("happo_cbf", k), get("sail_cbf", k))
                       for k in ("proposal_violation", "correction")}
    if "sail_cbf" in o and "sage" in o:
        out["talo"] = {"w_gap": _change(get("sail_cbf", "w_gap"), get("sage", "w_gap")),
                       "cos_ind_team": {"from": get("sail_cbf", "cos_ind_team"), "to": get("sage", "cos_ind_team")}}
    return out


def headline_markdown(h: dict) -> list[str]:
    def red(c):
        pct = c["reduction_pct"]
        if pct is None:
            return "no reduction to state: the reference is 0"
        return f"{pct:.1f}% lower" if pct >= 0 else f"{-pct:.1f}% higher"

    def arrow(c, digits=1, scale=1.0, unit=""):   # "from → to" of one comparison
        return f"{_fmt(c['from'], digits, scale)}{unit} → {_fmt(c['to'], digits, scale)}{unit}"

    lines = []
    if "shield" in h:
        sh = h["shield"]
        lines.append(f"- Exact CBF filtering (HAPPO → HAPPO+CBF): deployment Col./1k {arrow(sh['col_per_1k'], 2)} "
                     f"({red(sh['col_per_1k'])}); during training {arrow(sh['train_col_per_1k'], 2)} "
                     f"({red(sh['train_col_per_1k'])}); SR {arrow(sh['success_rate'], scale=100, unit='%')}.")
    if "sage_vs_shield" in h:
        sv = h["sage_vs_shield"]
        gain = (sv["success_rate"]["to"] - sv["success_rate"]["from"]) * 100
        lines.append(f"- SAGE+CBF vs HAPPO+CBF: SR {arrow(sv['success_rate'], scale=100, unit='%')} ({gain:+.1f} pp); "
                     f"DR {arrow(sv['drop_rate'], scale=100, unit='%')}.")
    if "sail" in h:
        sa = h["sail"]
        lines.append(f"- SAIL (HAPPO+CBF → SAIL+CBF): proposal violation "
                     f"{arrow(sa['proposal_violation'], scale=100, unit='%')} ({red(sa['proposal_violation'])}); "
                     f"correction {arrow(sa['correction'], 3)} ({red(sa['correction'])}).")
    if "talo" in h:
        ta = h["talo"]
        lines.append(f"- TALO (SAIL+CBF → SAGE+CBF, training means): W_gap {arrow(ta['w_gap'], 3)} "
                     f"({red(ta['w_gap'])}); cos(g_ind, g_team) {arrow(ta['cos_ind_team'], 3)}.")
    return lines


def _fmt(x: float, digits: int = 1, scale: float = 1.0) -> str:
    return "–" if x is None or math.isnan(x) else f"{x * scale:.{digits}f}"


def table_markdown(summary: dict) -> str:
    """Table I as Markdown: SR (%) and Col./1k per scenario, family means, overall row."""
    methods = summary["methods"]
    head = "| Family | Scenario | " + " | ".join(
        f"{METHOD_TITLES[m]} SR | {METHOD_TITLES[m]} Col./1k" for m in methods) + " |"
    sep = "|" + "---|" * (2 + 2 * len(methods))
    lines = ["### Per scenario (SR in %, Col./1k in collision steps per 1000 env steps)", "", head, sep]
    for fam, members in FAMILIES.items():
        for s in members:
            if s not in summary["scenarios"]:
                continue
            row = summary["scenarios"][s]
            lines.append(f"| {fam} | {SCENARIO_TITLES[s]} | " + " | ".join(
                f"{_fmt(row[m]['success_rate'], scale=100)} | {_fmt(row[m]['col_per_1k'])}" for m in methods) + " |")
        if fam in summary["families"]:
            row = summary["families"][fam]
            lines.append(f"| {fam} | **{fam} mean** | " + " | ".join(
                f"**{_fmt(row[m]['success_rate'], scale=100)}** | **{_fmt(row[m]['col_per_1k'])}**" for m in methods) + " |")
    lines += ["", "### Overall (mean ± std across runs)", "",
              "| Method | Runs | SR (%) | Return | Col./1k | DR (%) | Proposal viol. (%) | of which wall rows (%) "
              "| Correction |",
              "|---|---|---|---|---|---|---|---|---|"]
    for m in methods:
        o = summary["overall"][m]

        def pm(key, scale=1.0, digits=1):
            return f"{_fmt(o[key]['mean'], digits, scale)} ± {_fmt(o[key]['std'], digits, scale)}"
        viol = pm("proposal_violation", 100) if METHOD_SPECS[m].shielded else "N/A"
        wall_viol = pm("proposal_violation_any_wall", 100) if METHOD_SPECS[m].shielded else "N/A"
        corr = pm("correction", 1, 3) if METHOD_SPECS[m].shielded else "N/A"
        lines.append(f"| {METHOD_TITLES[m]} | {o['runs']} | {pm('success_rate', 100)} | {pm('return_mean', 1, 2)} | "
                     f"{pm('col_per_1k')} | {pm('drop_rate', 100)} | {viol} | {wall_viol} | {corr} |")
    if summary.get("headline"):
        lines += ["", "### Headline comparisons (the quantities of the paper's abstract, from the rows above)", ""]
        lines += headline_markdown(summary["headline"])
    if summary.get("train_scenarios"):
        lines += ["", "### Col./1k during training, per scenario (same budget)", "",
                  "| Scenario | " + " | ".join(METHOD_TITLES[m] for m in methods) + " |",
                  "|" + "---|" * (1 + len(methods))]
        for s, row in summary["train_scenarios"].items():
            lines.append(f"| {SCENARIO_TITLES[s]} | " + " | ".join(
                _fmt(row[m]["train_col_per_1k"], 2) for m in methods) + " |")
    lines += ["", "### During training (same budget; collision steps and drops the carriers went through while learning)", "",
              "| Method | Env steps | Col./1k | DR (%) |", "|---|---|---|---|"]
    for m in methods:
        o = summary["overall"][m]
        lines.append(f"| {METHOD_TITLES[m]} | {_fmt(o['train_env_steps']['mean'], 0)} | "
                     f"{_fmt(o['train_col_per_1k']['mean'], 2)} ± {_fmt(o['train_col_per_1k']['std'], 2)} | "
                     f"{_fmt(o['train_drop_rate']['mean'], 1, 100)} ± {_fmt(o['train_drop_rate']['std'], 1, 100)} |")
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


def write_figures(results: list[Result], summary: dict, out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    methods = summary["methods"]
    colors = dict(zip(METHODS, ["#7f7f7f", "#1f77b4", "#2ca02c", "#ff7f0e", "#d62728"]))
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
    panels = [("episode_return", "(a) episode return"), ("drop_rate", "(b) drop rate")]
    if any("deploy_sr" in p for r in results for p in r.train_curve):
        panels.append(("deploy_success_rate", "(c) deployment SR (probe: trees + exact QP)"))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.4))
    for (key, title), ax in zip(panels, axes):
        for m in methods:
            g, mu, sd = _curves(results, m, key)
            lo, hi = (mu - sd, mu + sd) if key == "episode_return" else (np.clip(mu - sd, 0, 1), np.clip(mu + sd, 0, 1))
            ax.plot(g, mu, color=colors[m], label=METHOD_TITLES[m]); ax.fill_between(g, lo, hi, color=colors[m], alpha=0.15)
        ax.set_title(title, fontsize=9); ax.set_xlabel("training progress")
    axes[0].legend(fontsize=7)
    fig.tight_layout(); path = out_dir / "reward_drop.png"; fig.savefig(path, dpi=130); plt.close(fig)
    written.append(path)

    # Fig. sail_talo_ablation: mechanism panels (a)-(d).
    panels = [("proposal_violation", "(a) proposal violation"), ("correction", "(b) proposal–execution correction"),
              ("w_gap", "(c) $W_{gap}$"), ("cos_ind_team", "(d) cos($g_{ind}$, $g_{team}$)")]
    fig, axes = plt.subplots(2, 2, figsize=(9, 6))
    for ax, (key, title) in zip(axes.flat, panels):
        for m in methods:
            if not METHOD_SPECS[m].shielded:
                continue
            g, mu, sd = _curves(results, m, key)
            ax.plot(g, mu, color=colors[m], label=METHOD_TITLES[m]); ax.fill_between(g, mu - sd, mu + sd, color=colors[m], alpha=0.15)
        ax.set_title(title, fontsize=9); ax.set_xlabel("training progress")
    if axes[0, 0].get_legend_handles_labels()[0]:
        axes[0, 0].legend(fontsize=7)
    fig.tight_layout(); path = out_dir / "sail_talo_ablation.png"; fig.savefig(path, dpi=130); plt.close(fig)
    written.append(path)

    # Fig. payload_panels: execution-level quality per method.
    keys = [("tilt", "(a) payload tilt"), ("heading_error", "(b) heading error"),
            ("height_error", "(c) height error"), ("completion_time", "(d) completion time")]
    fig, axes = plt.subplots(1, 4, figsize=(12, 3))
    for ax, (key, title) in zip(axes, keys):
        mus = [summary["overall"][m][key]["mean"] for m in methods]
        sds = [summary["overall"][m][key]["std"] for m in methods]
        ax.bar(range(len(methods)), mus, yerr=sds, color=[colors[m] for m in methods], capsize=2)
        ax.set_xticks(range(len(methods))); ax.set_xticklabels([METHOD_TITLES[m] for m in methods], rotation=45, fontsize=7)
        ax.set_title(title, fontsize=9)
    fig.tight_layout(); path = out_dir / "payload_panels.png"; fig.savefig(path, dpi=130); plt.close(fig)
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
