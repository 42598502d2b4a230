"""`sage eval`: deployment evaluation with what deployment keeps.

Deployment keeps only the hard trees' deterministic actions and the exact
joint CBF-QP (Sec. III-D: SAIL, exploration, the critic and TALO are
training-only), so this loads the tree parameters of a run's newest
checkpoint and runs ``common.evaluation.deployment.evaluate_policy`` on seeded episodes
disjoint from training. Output keys follow the report's ``EVAL_KEYS``. ``--video``
renders one of the scored episodes (``common.evaluation.video``).
"""
from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

from common.algos.registry import method_spec
from common.audit.recording import Recorder
from common.env.scenarios import SCENARIOS
from common.evaluation import video as video_lib
from common.evaluation.deployment import evaluate_policy
from common.evaluation.video import EXTRA_HINT, SUFFIXES, VIEWS, VideoConfig, VideoRecorder
from common.status import Progress
from sage.errors import UsageError, nonneg_int, output_file, positive_float, positive_int, user_input
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
    # pooled collision figures (violation steps / all steps) and how the episodes ended, apart
    for k in ("col_per_1k_pooled", "margin_col_per_1k_pooled", "margin_violation_steps", "truncation_rate",
              "timeout_rate", "deadlock_rate"):
        if k in e:
            out[k] = e[k]
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


class _Recorders:
    """Several deployment recorders fed by one loop (``--record`` and ``--video`` together)."""

    def __init__(self, *recorders):
        self.recorders = [r for r in recorders if r is not None]

    def on_step(self, *step) -> None:
        for r in self.recorders:
            r.on_step(*step)

    def on_episode(self, k: int, metrics: dict) -> None:
        for r in self.recorders:
            r.on_episode(k, metrics)


def video_config(args) -> VideoConfig:
    """The ``--video*`` flags checked before any work: file type, the video extra, the view
    (default: camera where OpenGL works, else top-down with a one-line note)."""
    suffix = Path(args.video).suffix.lower()
    if suffix not in SUFFIXES:
        raise UsageError(f"--video {args.video}: videos are {' or '.join(SUFFIXES)} files")
    missing = video_lib.missing_dependency(suffix)
    if missing:
        raise UsageError(f"--video needs the video extra ({missing} is missing): {EXTRA_HINT}")
    if args.video_episode >= args.episodes:
        raise UsageError(f"--video-episode {args.video_episode}: only {args.episodes} episodes are evaluated")
    view = args.video_view
    why = video_lib.gl_unavailable() if view != "topdown" else None
    if view == "camera" and why:
        raise UsageError(f"--video-view camera needs OpenGL, unavailable here ({why}); use --video-view topdown")
    with user_input("--video"):
        cfg = VideoConfig(view=view or ("topdown" if why else "camera"), episode=args.video_episode,
                          width=args.video_width, every=args.video_every, fps=args.video_fps)
    output_file(args.video, "--video")
    if view is None and why:   # the note only once every flag passed: a usage error stays one line
        print(f"sage eval: no OpenGL for the camera view ({why}); rendering the top-down view",
              file=sys.stderr, flush=True)
    return cfg


def run_eval_command(args) -> int:
    if args.record and Path(args.record).suffix != ".npz":
        raise UsageError(f"--record {args.record}: recordings are .npz files")
    video_cfg = video_config(args) if args.video else None
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
    video = None if video_cfg is None else VideoRecorder(
        args.video, video_cfg, title=f"{cfg.method} on {env_cfg.scenario}, version {version}, "
                                     f"episode {video_cfg.episode} (seed {args.seed})")
    bar = Progress(sys.stderr, args.episodes, "sage eval", unit="episodes")

    def on_step(finished: int, step: int, limit: int) -> None:
        # every episode has ended by the step limit: the ETA is an upper bound
        elapsed = bar.clock() - bar.t0
        bar.update(finished, note=f"step {step}/{limit}", eta_s=elapsed / step * (limit - step))

    try:
        raw = evaluate_policy(params, env_cfg, args.episodes, seed=args.seed, shielded=shielded,
                              recorder=_Recorders(recorder, video) if video else recorder, on_step=on_step)
    finally:
        bar.close()
        written = video.close() if video else None
    rec = eval_record(raw)
    rec.update(method=cfg.method, scenario=cfg.scenario, version=version, human_slot=env_cfg.human_slot,
               differs_from_training=diff)
    if recorder is not None:
        recording = recorder.recording(params, env_cfg, args.seed, shielded)
        rec["recording"] = str(recording.save(args.record))
    if written is not None:
        rec["video"] = written["path"]
        print(f"sage eval: video {written['path']} ({written['frames']} frames, {written['view']} view)",
              file=sys.stderr)
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
    p.add_argument("--video", default=None, metavar="FILE.mp4|FILE.gif",
                   help="also render one evaluated episode: proposed vs executed commands, leaves, outcome "
                        f"(needs the video extra: {EXTRA_HINT})")
    p.add_argument("--video-view", default=None, choices=VIEWS,
                   help="camera: MuJoCo offscreen render tracking the payload (OpenGL; EGL when headless); "
                        "topdown: 2-D drawing, no GL; default: camera where OpenGL works, else topdown")
    p.add_argument("--video-episode", type=nonneg_int, default=0, help="which evaluated episode (default: the first)")
    p.add_argument("--video-every", type=positive_int, default=1, help="one frame every N steps (smaller files)")
    p.add_argument("--video-width", type=positive_int, default=480, help="frame width in pixels, 160..640")
    p.add_argument("--video-fps", type=positive_float, default=None,
                   help="frames per second (default: real time, 1 / (control_dt * every))")
    p.add_argument("--json", action="store_true",
                   help="print the evaluation record (every deployment metric) as one JSON object on stdout "
                        "instead of the summary line; progress stays on stderr")
    p.set_defaults(func=run_eval_command)
