"""`sage eval`: deployment evaluation with what deployment keeps.

Deployment keeps only the hard trees' deterministic actions and the exact
joint CBF-QP (Sec. III-D: SAIL, exploration, the critic and TALO are
training-only), so this loads the tree parameters of a run's newest
checkpoint and runs ``common.evaluation.deployment.evaluate_policy`` on seeded episodes
disjoint from training. Output keys follow the report's ``EVAL_KEYS``.
"""
from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

from common.algos.registry import method_spec
from common.audit.recording import Recorder
from common.env.scenarios import SCENARIOS
from common.evaluation.deployment import evaluate_policy
from common.status import Progress
from sage.errors import UsageError, nonneg_int, positive_int, user_input
from sage.runs import load_run
from services.config import FINAL_EVAL_SEED


def eval_record(e: dict) -> dict:
    """Map ``evaluate_policy`` output onto the report's result keys (+ stds)."""
    out = {k: e.get(k) for k in (
        "success_rate", "return_mean", "col_per_1k", "margin_col_per_1k", "drop_rate", "tilt", "heading_error",
        "height_error", "completion_time", "min_clearance", "progress_per_step")}
    for k in list(out):
        if f"{k}_std" in e:
            out[f"{k}_std"] = e[f"{k}_std"]
    out["proposal_violation"] = e.get("proposal_violation_rate")
    for kind, rate in (e.get("proposal_violation_by_kind") or {}).items():
        out[f"proposal_violation_{kind}"] = rate
    out["correction"] = e.get("correction_mean")
    out["intervention_rate"] = e.get("intervention_rate")
    out["infeasible_steps"] = e.get("infeasible_steps")
    out["episodes"] = e.get("episodes_finished")
    out["shielded"] = e.get("shielded")
    out["seed"] = e.get("seed")
    return out


def _team(slot) -> str:
    return "three robots" if slot is None else f"a human in slot {slot}"


def training_differences(trained_env, method: str, env_cfg, shielded: bool) -> dict:
    """What this evaluation (``env_cfg``, ``shielded``) changes from the run's saved
    configuration (``trained_env``, ``method``): scenario, human slot, shield on/off,
    each as ``{"eval": ..., "trained": ...}``."""
    diff = {}
    if env_cfg.scenario != trained_env.scenario:
        diff["scenario"] = {"eval": env_cfg.scenario, "trained": trained_env.scenario}
    if env_cfg.human_slot != trained_env.human_slot:
        diff["human_slot"] = {"eval": env_cfg.human_slot, "trained": trained_env.human_slot}
    trained_shielded = method_spec(method).shielded
    if shielded != trained_shielded:
        diff["shielded"] = {"eval": shielded, "trained": trained_shielded}
    return diff


def differences_notice(diff: dict) -> str | None:
    """``sage eval: evaluating on tilt_gate (trained on narrow_gate); unshielded (trained shielded)``."""
    parts = []
    if "scenario" in diff:
        parts.append(f"evaluating on {diff['scenario']['eval']} (trained on {diff['scenario']['trained']})")
    if "human_slot" in diff:
        parts.append(f"with {_team(diff['human_slot']['eval'])} (trained with {_team(diff['human_slot']['trained'])})")
    if "shielded" in diff:
        on = {True: "shielded", False: "unshielded"}
        parts.append(f"{on[diff['shielded']['eval']]} (trained {on[diff['shielded']['trained']]})")
    return "sage eval: " + "; ".join(parts) if parts else None


def run_eval_command(args) -> int:
    if args.record and Path(args.record).suffix != ".npz":
        raise UsageError(f"--record {args.record}: recordings are .npz files")
    with user_input(args.checkpoint):
        cfg, params, version = load_run(args.checkpoint)
    trained_env = cfg.env_config()
    with user_input():
        if args.scenario:
            cfg.scenario = args.scenario
        env_cfg = cfg.env_config()
        if getattr(args, "human_slot", None) is not None:
            # a robot-trained team deployed beside a human: the same trees drive the
            # other two slots, the QP holds the human's block fixed (Eq. qpshield)
            env_cfg = dataclasses.replace(
                env_cfg, human_slot=None if args.human_slot == "none" else int(args.human_slot))
    shielded = not args.unshielded
    diff = training_differences(trained_env, cfg.method, env_cfg, shielded)
    notice = differences_notice(diff)
    if notice:
        print(notice, file=sys.stderr, flush=True)
    recorder = Recorder() if args.record else None   # records the very episodes it scores
    bar = Progress(sys.stderr, args.episodes, "sage eval", unit="episodes")

    def on_step(finished: int, step: int, limit: int) -> None:
        # every episode has ended by the step limit: the ETA is an upper bound
        elapsed = bar.clock() - bar.t0
        bar.update(finished, note=f"step {step}/{limit}", eta_s=elapsed / step * (limit - step))

    try:
        raw = evaluate_policy(params, env_cfg, args.episodes, seed=args.seed, shielded=shielded, recorder=recorder,
                              on_step=on_step)
    finally:
        bar.close()
    rec = eval_record(raw)
    rec.update(method=cfg.method, scenario=cfg.scenario, version=version, human_slot=env_cfg.human_slot,
               differs_from_training=diff)
    if recorder is not None:
        recording = recorder.recording(params, env_cfg, args.seed, shielded)
        rec["recording"] = str(recording.save(args.record))
    if args.json:
        print(json.dumps(rec, indent=2, default=float))
    else:
        def f(key, scale=1.0):
            v = rec.get(key)
            return "n/a" if v is None else f"{v * scale:.2f}"
        print(f"{cfg.method} on {cfg.scenario} (version {version}, {rec['episodes']} episodes, "
              f"{'exact QP' if shielded else 'unshielded'}"
              f"{'' if env_cfg.human_slot is None else f', human in slot {env_cfg.human_slot}'}): SR {f('success_rate', 100)}%  "
              f"return {f('return_mean')}  Col/1k {f('col_per_1k')}  DR {f('drop_rate', 100)}%  "
              f"proposal viol. {f('proposal_violation', 100)}%  correction {f('correction')}", file=sys.stderr)
        print(json.dumps(rec, default=float))
    return 0


def register(commands, bench) -> None:
    p = commands.add_parser("eval", help="deployment evaluation: hard trees + exact QP only")
    p.add_argument("checkpoint", help="run directory or checkpoint file")
    p.add_argument("--episodes", type=positive_int, default=100)
    p.add_argument("--seed", type=nonneg_int, default=FINAL_EVAL_SEED,
                   help="evaluation seeds start here (disjoint from training)")
    p.add_argument("--scenario", default=None, choices=sorted(SCENARIOS), help="override the run's scenario")
    p.add_argument("--unshielded", action="store_true", help="execute the trees' actions without the QP")
    p.add_argument("--human-slot", default=None, choices=["0", "1", "2", "none"],
                   help="deploy beside the scripted human partner in this carrier slot (its block is "
                        "exogenous: noisy, delayed, never corrected by the QP); 'none' = three "
                        "robots; default: the run's own setting")
    p.add_argument("--record", default=None, help="also record decision traces to this file")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run_eval_command)
