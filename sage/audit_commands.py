"""`sage tree`, `sage trace`, `sage audit`, `sage export-bundle` (Sec. IV-C auditability)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from common.audit import tree_view
from common.audit.bundle import export_bundle
from common.audit.config import AuditConfig
from common.audit.figures import colortrace, draw_trace
from common.audit.leaf_stats import audit_markdown, leaf_audit
from common.audit.params import feature_names, load_params_file, split_carriers
from common.audit.recording import Recording
from common.checkpoint import list_checkpoints
from common.rundir import RunDir

_DEFAULTS = AuditConfig()


def register(commands, bench) -> None:
    p = commands.add_parser("tree", help="show or export a carrier's hard tree with named predicates")
    p.add_argument("action", choices=["show", "export"], help="show prints (text/json/dot); export writes --out")
    p.add_argument("policy", help="checkpoint, run directory, flat params .npz/.json, or bundle trees.json")
    p.add_argument("--carrier", type=int, default=0)
    p.add_argument("--format", choices=["text", "json", "dot", "png"], default="text")
    p.add_argument("--eval-log", default=None, help="a recording (.npz) whose leaf visits to count")
    p.add_argument("--out", default=None, help="output file (required for png)")
    p.add_argument("--top-terms", type=int, default=_DEFAULTS.top_terms)
    p.set_defaults(func=_tree)

    p = commands.add_parser("trace", help="draw two recorded root-to-leaf decisions (Fig. tree)")
    p.add_argument("recording", help="recording .npz from `sage eval --record`")
    p.add_argument("--out", default="trace.png")
    p.add_argument("--carrier", type=int, default=0)
    p.add_argument("--steps", default=None, help="two step indices 'S1,S2' (default: representative pair)")
    p.set_defaults(func=_trace)

    p = commands.add_parser("audit", help="leaf-tuple audit: purity, NMI, shuffle z, occupancy figures")
    p.add_argument("recording")
    p.add_argument("--out", default="results/audit")
    p.add_argument("--bins", type=int, default=_DEFAULTS.progress_bins)
    p.add_argument("--shuffles", type=int, default=_DEFAULTS.shuffles)
    p.add_argument("--top-tuples", type=int, default=_DEFAULTS.top_tuples)
    p.add_argument("--seed", type=int, default=_DEFAULTS.seed)
    p.add_argument("--episode", type=int, default=None, help="episode for panel (b) (default: furthest)")
    p.set_defaults(func=_audit)

    p = commands.add_parser("export-bundle", help="write a numpy-only deployment bundle (trees + CBF-QP)")
    p.add_argument("policy", help="checkpoint, run directory or flat params .npz/.json")
    p.add_argument("out", help="output directory")
    p.set_defaults(func=_export_bundle)


def load_policy(path: str) -> dict[str, np.ndarray]:
    """Flat params from a checkpoint file, a run directory holding one, or .npz/.json."""
    p = Path(path)
    if p.is_dir():
        # a run directory: its newest checkpoint (by version); else a folder of params files
        candidates = list_checkpoints(RunDir(p).checkpoints) or sorted(
            [*p.glob("*.pt"), *p.glob("*.npz")], key=lambda q: q.stat().st_mtime)
        if not candidates:
            raise FileNotFoundError(f"{p}: no checkpoint (*.pt) or params (*.npz) inside")
        p = candidates[-1]  # newest
    return load_params_file(p)


def leaf_visits(log_path: str, carrier: int, n_leaves: int) -> np.ndarray:
    """Per-leaf visit counts of one carrier from a recording (or any .npz with a 'leaf' [S, N] array)."""
    with np.load(log_path, allow_pickle=False) as data:
        if "leaf" not in data.files:
            raise ValueError(f"{log_path}: no 'leaf' array; pass a recording from `sage eval --record`")
        leaf = np.asarray(data["leaf"])
    if leaf.ndim != 2 or not 0 <= carrier < leaf.shape[1]:
        raise ValueError(f"{log_path}: leaf array {leaf.shape} has no carrier {carrier}")
    if leaf.size and (leaf.min() < 0 or leaf.max() >= n_leaves):
        raise ValueError(f"{log_path}: leaf ids outside 0..{n_leaves - 1}; recorded with another tree?")
    return np.bincount(leaf[:, carrier].astype(np.int64), minlength=n_leaves)


def _tree(args: argparse.Namespace) -> int:
    params = load_policy(args.policy)
    trees = split_carriers(params)
    if not 0 <= args.carrier < len(trees):
        raise SystemExit(f"--carrier {args.carrier} out of range 0..{len(trees) - 1}")
    tree = trees[args.carrier]
    visits = None if args.eval_log is None else leaf_visits(args.eval_log, args.carrier, tree.n_leaves)
    desc = tree_view.describe_tree(tree, feature_names(tree.obs_dim), AuditConfig(top_terms=args.top_terms), visits)
    title = f"carrier {args.carrier} tree ({Path(args.policy).name})"
    if args.format == "png":
        out = args.out or f"tree_carrier{args.carrier}.png"
        tree_view.tree_png(desc, out, title)
        print(out)
        return 0
    text = {"text": lambda: tree_view.tree_text(desc, title), "json": lambda: tree_view.tree_json(desc),
            "dot": lambda: tree_view.tree_dot(desc, title)}[args.format]()
    if args.action == "export" or args.out:
        suffix = "txt" if args.format == "text" else args.format
        out = args.out or f"tree_carrier{args.carrier}.{suffix}"
        Path(out).write_text(text + "\n")
        print(out)
    else:
        sys.stdout.write(text + "\n")
    return 0


def _trace(args: argparse.Namespace) -> int:
    rec = Recording.load(args.recording)
    steps = None
    if args.steps:
        steps = [int(s) for s in args.steps.split(",")]
        if len(steps) != 2 or not all(0 <= s < rec.n_steps for s in steps):
            raise SystemExit(f"--steps needs two indices in 0..{rec.n_steps - 1}")
    used = draw_trace(rec, args.out, args.carrier, steps)
    print(json.dumps({"figure": args.out, "steps": used,
                      "leaves": [int(rec.leaf[s, args.carrier]) for s in used]}))
    return 0


def run_audit(recording, out_dir: str | Path, cfg: AuditConfig = AuditConfig(), episode: int | None = None) -> dict:
    """Table leaf_interpretability (JSON + Markdown) and Fig. colortrace for one recording."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = leaf_audit(recording.leaf, recording.progress, cfg)
    result["episodes"] = recording.n_episodes
    result["figure"] = colortrace(recording, str(out / "colortrace.png"), cfg, episode)
    (out / "leaf_audit.json").write_text(json.dumps(result, indent=1))
    (out / "leaf_audit.md").write_text(audit_markdown(result) + "\n")
    return result


def _audit(args: argparse.Namespace) -> int:
    cfg = AuditConfig(progress_bins=args.bins, shuffles=args.shuffles, top_tuples=args.top_tuples, seed=args.seed)
    result = run_audit(Recording.load(args.recording), args.out, cfg, args.episode)
    print(audit_markdown(result))
    print(f"wrote {args.out}/leaf_audit.json, leaf_audit.md, colortrace.png")
    return 0


def _export_bundle(args: argparse.Namespace) -> int:
    out = export_bundle(load_policy(args.policy), args.out, meta={"source": str(args.policy)})
    print(f"wrote bundle to {out}: {', '.join(sorted(p.name for p in out.iterdir()))}")
    return 0
