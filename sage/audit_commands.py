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
from common.audit.params import BadPolicyParams, feature_names, feature_units_of, load_params_file, split_carriers
from common.audit.recording import Recording
from common.audit.safe_npz import load_npz
from common.checkpoint import list_checkpoints
from common.rundir import RunDir
from sage.errors import (UsageError, load_error, nonneg_int, output_dir, output_file, positive_int,
                         user_input)
from sage.runs import CHECKPOINT_LOAD_ERRORS

# What load_params_file raises on a corrupt or foreign file (torch, numpy or json underneath).
POLICY_LOAD_ERRORS = CHECKPOINT_LOAD_ERRORS + (KeyError, TypeError, OSError)

_DEFAULTS = AuditConfig()


def register(commands, bench) -> None:
    p = commands.add_parser("tree", help="show or export a carrier's hard tree with named predicates")
    p.add_argument("action", choices=["show", "export"],
                   help="show prints text/json/dot on stdout (or writes --out); export writes a file; "
                        "png is always a file")
    p.add_argument("policy", help="checkpoint, run directory, flat params .npz/.json, or bundle trees.json")
    p.add_argument("--carrier", type=nonneg_int, default=0)
    p.add_argument("--format", choices=["text", "json", "dot", "png"], default="text")
    p.add_argument("--eval-log", default=None, help="a recording (.npz) whose leaf visits to count")
    p.add_argument("--out", default=None,
                   help="output file (default for png and export: tree_carrier<N>.<format> in the current directory)")
    p.add_argument("--top-terms", type=positive_int, default=_DEFAULTS.top_terms)
    p.set_defaults(func=_tree)

    p = commands.add_parser("trace", help="draw two recorded root-to-leaf decisions (Fig. tree)")
    p.add_argument("recording", help="recording .npz from `sage eval --record`")
    p.add_argument("--out", default="trace.png")
    p.add_argument("--carrier", type=nonneg_int, default=0)
    p.add_argument("--steps", default=None, help="two step indices 'S1,S2' (default: representative pair)")
    p.set_defaults(func=_trace)

    p = commands.add_parser("audit", help="leaf-tuple audit: purity, NMI, shuffle z, occupancy figures")
    p.add_argument("recording")
    p.add_argument("--out", default="results/audit")
    p.add_argument("--bins", type=nonneg_int, default=_DEFAULTS.progress_bins)
    p.add_argument("--shuffles", type=nonneg_int, default=_DEFAULTS.shuffles)
    p.add_argument("--top-tuples", type=positive_int, default=_DEFAULTS.top_tuples)
    p.add_argument("--seed", type=nonneg_int, default=_DEFAULTS.seed)
    p.add_argument("--episode", type=nonneg_int, default=None, help="episode for panel (b) (default: furthest)")
    p.set_defaults(func=_audit)

    p = commands.add_parser("export-bundle", help="write a numpy-only deployment bundle (trees + CBF-QP)")
    p.add_argument("policy", help="checkpoint, run directory or flat params .npz/.json")
    p.add_argument("out", help="output directory")
    p.set_defaults(func=_export_bundle)


def load_policy(path: str) -> dict[str, np.ndarray]:
    """Flat params from a checkpoint file, a run directory holding one, or .npz/.json.

    A missing path is a ``FileNotFoundError``; a file that does not load or holds
    no valid trees a ``ValueError`` naming it. In a run directory an unreadable
    newest checkpoint falls back to the previous one (as ``sage eval`` does)."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(2, "No such file or directory", str(p))
    if not p.is_dir():
        return _load_policy_file(p)
    # a run directory: its newest checkpoint (by version); else a folder of params files
    candidates = list_checkpoints(RunDir(p).checkpoints) or sorted(
        [*p.glob("*.pt"), *p.glob("*.npz")], key=lambda q: q.stat().st_mtime)
    if not candidates:
        raise FileNotFoundError(f"{p}: no checkpoint (*.pt) or params (*.npz) inside")
    first_error = None
    for candidate in reversed(candidates):  # newest first
        try:
            return _load_policy_file(candidate)
        except ValueError as exc:
            first_error = first_error or exc
    raise first_error


def _load_policy_file(p: Path) -> dict[str, np.ndarray]:
    try:
        return load_params_file(p)
    except BadPolicyParams as exc:
        msg = str(exc)
        raise BadPolicyParams(msg if str(p) in msg else f"{p}: {msg}") from exc
    except FileNotFoundError:
        raise
    except POLICY_LOAD_ERRORS as exc:
        raise load_error(p, "policy file (checkpoint, .npz or .json params)", exc) from exc


def load_recording(path: str) -> Recording:
    """``Recording.load``; a missing, corrupt or foreign file is a ``UsageError`` naming it."""
    p = Path(path)
    if p.is_dir():
        raise UsageError(f"{p} is a directory; pass a recording .npz from `sage eval --record`")
    with user_input(str(p)):
        try:
            return Recording.load(p)
        except FileNotFoundError:
            raise
        except POLICY_LOAD_ERRORS as exc:
            raise load_error(p, "recording (.npz from `sage eval --record`)", exc) from exc


def leaf_visits(log_path: str, carrier: int, n_leaves: int) -> np.ndarray:
    """Per-leaf visit counts of one carrier from a recording (or any .npz with a 'leaf' [S, N] array)."""
    data = load_npz(log_path, _DEFAULTS.max_npz_bytes)   # npy headers checked before allocating
    if "leaf" not in data:
        raise ValueError(f"{log_path}: no 'leaf' array; pass a recording from `sage eval --record`")
    leaf = np.asarray(data["leaf"])
    if leaf.ndim != 2 or not 0 <= carrier < leaf.shape[1]:
        raise ValueError(f"{log_path}: leaf array {leaf.shape} has no carrier {carrier}")
    if leaf.size and (leaf.min() < 0 or leaf.max() >= n_leaves):
        raise ValueError(f"{log_path}: leaf ids outside 0..{n_leaves - 1}; recorded with another tree?")
    return np.bincount(leaf[:, carrier].astype(np.int64), minlength=n_leaves)


def _tree(args: argparse.Namespace) -> int:
    if args.out:
        output_file(args.out, "--out", figure=args.format == "png")
    with user_input(args.policy):
        params = load_policy(args.policy)
        trees = split_carriers(params)
    if not 0 <= args.carrier < len(trees):
        raise UsageError(f"--carrier {args.carrier} out of range 0..{len(trees) - 1}")
    tree = trees[args.carrier]
    visits = None
    if args.eval_log is not None:
        if not Path(args.eval_log).is_file():
            raise UsageError(f"--eval-log {args.eval_log}: no such file")
        with user_input():   # the messages name the file
            try:
                visits = leaf_visits(args.eval_log, args.carrier, tree.n_leaves)
            except POLICY_LOAD_ERRORS as exc:
                if isinstance(exc, ValueError) and str(args.eval_log) in str(exc):
                    raise
                raise load_error(args.eval_log, "recording (.npz)", exc) from exc
    names = feature_names(tree.obs_dim)
    desc = tree_view.describe_tree(tree, names, AuditConfig(top_terms=args.top_terms), visits, feature_units_of(names))
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
    steps = None
    if args.steps:
        try:
            steps = [int(s) for s in args.steps.split(",")]
        except ValueError:
            raise UsageError(f"--steps {args.steps!r}: expected two step indices 'S1,S2'") from None
        if len(steps) != 2:
            raise UsageError(f"--steps {args.steps!r}: expected two step indices 'S1,S2'")
    output_file(args.out, "--out", figure=True)
    rec = load_recording(args.recording)
    if steps is not None and not all(0 <= s < rec.n_steps for s in steps):
        raise UsageError(f"--steps {args.steps}: needs two indices in 0..{rec.n_steps - 1}")
    n_carriers = rec.leaf.shape[1] if rec.leaf.ndim == 2 else 0
    if not 0 <= args.carrier < n_carriers:
        raise UsageError(f"--carrier {args.carrier} out of range 0..{n_carriers - 1}")
    used = draw_trace(rec, args.out, args.carrier, steps)
    print(json.dumps({"figure": args.out, "steps": used,
                      "leaves": [int(rec.leaf[s, args.carrier]) for s in used]}))
    return 0


AUDIT_FILES = ("leaf_audit.json", "leaf_audit.md", "colortrace.png")   # what run_audit writes


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
    with user_input():
        cfg = AuditConfig(progress_bins=args.bins, shuffles=args.shuffles, top_tuples=args.top_tuples,
                          seed=args.seed)
    rec = load_recording(args.recording)
    if args.episode is not None and args.episode not in set(np.unique(rec.episode).tolist()):
        raise UsageError(f"--episode {args.episode}: not in the recording ({rec.n_episodes} episode(s))")
    output_dir(args.out, "--out", files=AUDIT_FILES)
    result = run_audit(rec, args.out, cfg, args.episode)
    print(audit_markdown(result))
    print(f"wrote {args.out}/leaf_audit.json, leaf_audit.md, colortrace.png")
    return 0


def _export_bundle(args: argparse.Namespace) -> int:
    with user_input(args.policy):
        params = load_policy(args.policy)
    output_dir(args.out, "out", files=("trees.json", "bundle_runtime.py", "README.md"))
    out = export_bundle(params, args.out, meta={"source": str(args.policy)})
    print(f"wrote bundle to {out}: {', '.join(sorted(p.name for p in out.iterdir()))}")
    return 0
