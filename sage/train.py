"""``sage train`` (the main job: in-process services by default, supervised
processes, or processes placed on a Ray cluster) and ``sage up`` (the supervisor
alone, e.g. one host's share of a run, or the whole run on a Ray cluster).

Every default comes from ``services.config.TrainConfig``; the flags only
override it.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import typing
from pathlib import Path

import numpy as np

from common.algos.registry import method_spec
from common.checkpoint import load_latest, load_newest
from common.evaluation.deployment import evaluate_policy
from common.policy.tree_torch import policy_params_from_checkpoint
from common.rundir import RunDir, atomic_write_text
from deploy import ray_run
from deploy.ray_run import ClusterError, RayPlacement, run_on_ray
from deploy.supervised_run import METRICS_OFFSETS, default_actor_count, parse_ids, run_supervised
from deploy.supervisor import EXIT_GAVE_UP, SupervisorConfig
from deploy.threads import run_inprocess
from common.config_fields import check_range, field_help, parse_value
from sage.errors import UsageError, nonneg_int, one_line, port, positive_int, user_input
from sage.runs import last_progress, load_run, read_config
from services.config import FINAL_EVAL_SEED, UNLIMITED_UPDATES, TrainConfig
from services.launcher import ROLES
from services.learner.tracking import (WANDB_HINT, MetricsTail, TrackingConfig, WandbRun, tensorboard_available,
                                       wandb_available)


# Flags of `sage train` that set a TrainConfig field of the same name: derived from the
# field (its type, range or choices, help and default), and applied only when typed, so
# `--config FILE --seed 3` runs FILE's config with seed 3 and nothing else changed.
TRAIN_FLAGS = ("scenario", "method", "updates", "minutes", "actors", "shields", "envs_per_actor", "chunk_len",
               "max_lag", "seed", "run_id", "run_dir", "eval_episodes")
# `sage up`'s fresh-run flags (the rest of its flags place services, not configure the run)
UP_FLAGS = ("scenario", "method", "updates", "minutes", "envs_per_actor", "seed", "run_id", "run_dir")


def add_config_flags(p, names) -> None:
    """``--NAME`` for each TrainConfig field in ``names``, default None (not given)."""
    d = TrainConfig()
    by_name = {f.name: f for f in dataclasses.fields(TrainConfig)}
    hints = typing.get_type_hints(TrainConfig)
    for name in names:
        f = by_name[name]
        default = getattr(d, name)
        help_text = field_help(f) + (f" (default {default})" if default not in ("", None) else "")
        p.add_argument("--" + name.replace("_", "-"), dest=name, default=None, type=_flag_type(f, hints[name]),
                       choices=f.metadata.get("choices"), help=help_text)


def _flag_type(f: dataclasses.Field, hint):
    """argparse ``type=`` of a field's flag: the text as the field's type, in its range."""
    def parse(text: str):
        try:
            value = parse_value(text, hint, "--" + f.name.replace("_", "-"))
            check_range(f, value, "--" + f.name.replace("_", "-"))
        except ValueError as exc:
            wanted = str(exc).split(" must be ", 1)[-1].rsplit(", got ", 1)[0]
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text!r}") from None
        return value
    parse.__name__ = f.name
    return parse


def apply_config_flags(cfg: TrainConfig, args, names) -> None:
    """The flags of ``names`` the user gave, onto ``cfg``."""
    for name in names:
        value = getattr(args, name)
        if value is not None:
            cfg.set(name, value)


def register(commands, bench) -> None:
    p = commands.add_parser("train", help="train a method with actor/shield/learner services")
    add_config_flags(p, TRAIN_FLAGS)
    p.add_argument("--mode", default=None, choices=("inprocess", "supervised", "ray"),
                   help="where the services run (default: the config's, inprocess for a fresh run); "
                        "ray: the supervised processes placed on a Ray cluster (--ray; extra .[cluster])")
    p.add_argument("--metrics-port", type=port, default=None,
                   help="Prometheus port (in-process registry); 0 = off (default)")
    p.add_argument("--config", default=None,
                   help="run a saved config JSON (e.g. runs/<id>/config.json); only the flags and --set given "
                        "here change it")
    p.add_argument("--human-slot", type=int, default=None, choices=(0, 1, 2),
                   help="put the scripted human partner in this carrier slot (exogenous, no tree)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a config field, e.g. --set algo.actor_lr=1e-3 --set env.max_steps=400 "
                        "--set shield.window_s=0.001 --set train.deploy_probe_every=10 (value parsed as JSON, else string)")
    p.add_argument("--quiet", action="store_true", help="no live progress line")
    add_ray_arguments(p, "implies --mode ray; default with --mode ray: auto")
    add_tracking_arguments(p)
    p.set_defaults(func=cmd_train)

    p = commands.add_parser("up", help="run learner, shield and actors as supervised processes (restarts, "
                                       "clean shutdown, live status)")
    add_up_arguments(p)
    p.set_defaults(func=cmd_up)


def add_ray_arguments(p, note: str) -> None:
    """``--ray ADDRESS`` and ``--ray-resources`` (``sage train``, ``sage up``); ``note`` ends the help."""
    p.add_argument("--ray", default=None, metavar="ADDRESS",
                   help=f"place the services on the Ray cluster at ADDRESS: auto (a running cluster), HOST:PORT "
                        f"(its head) or local (a fresh one-machine instance); {note} (deploy/README.md, \"Ray cluster\")")
    p.add_argument("--ray-resources", action="append", default=[], metavar="SERVICE=RESOURCE:AMOUNT",
                   help="extra Ray resources of a service (actor-1) or role (actor), e.g. to pin it to the nodes "
                        "that have a custom resource: --ray-resources learner=gpu_host:1 (repeatable)")


def add_tracking_arguments(p) -> None:
    """``--track`` (Weights & Biases) and its project/entity/group (``TrackingConfig``)."""
    d = TrackingConfig()
    p.add_argument("--track", action="store_true",
                   help="also log the run to Weights & Biases (metrics by section against env steps, the resolved "
                        f"config, the final evaluation; extra: {WANDB_HINT}); WANDB_MODE=offline needs no network")
    p.add_argument("--wandb-project", default=d.project, help="W&B project (default %(default)s)")
    p.add_argument("--wandb-entity", default=d.entity, help="W&B entity (default: your W&B default)")
    p.add_argument("--wandb-group", default=d.group, help="W&B group, e.g. a suite's name")


def tracking_config(args) -> TrackingConfig | None:
    """The W&B settings of ``--track`` (None without it); no wandb installed is a ``UsageError``."""
    if not getattr(args, "track", False):
        return None
    if not wandb_available():
        raise UsageError(f"--track logs to Weights & Biases, which is not installed: {WANDB_HINT}")
    return TrackingConfig(project=args.wandb_project, entity=args.wandb_entity, group=args.wandb_group)


def start_tracking(track: TrackingConfig | None, cfg: TrainConfig, run: RunDir):
    """A W&B run fed from the run's metrics file by a ``MetricsTail`` thread, or None."""
    if track is None:
        return None
    try:
        wb = WandbRun(track, cfg.run_id, run.root, json.loads(cfg.to_json()))
    except Exception as exc:  # noqa: BLE001 - wandb's own errors (no login, no network): one line
        raise UsageError(f"--track: Weights & Biases did not start a run ({one_line(exc)}); "
                         "WANDB_MODE=offline logs locally without an account") from None
    print(f"wandb: run {cfg.run_id} in project {track.project} ({wb.run.settings.mode} mode, "
          f"files in {wb.run.dir})", file=sys.stderr)
    return wb, MetricsTail(run.metrics_jsonl, wb.log, track.poll_s).start()


def stop_tracking(tracking, summary: dict | None) -> None:
    if tracking is not None:
        wb, tail = tracking
        tail.stop()
        wb.finish(summary)


def ray_placement(args, max_restarts: int | None = None) -> RayPlacement:
    """The Ray placement of ``--ray``/``--ray-resources``; bad values are a ``UsageError``."""
    with user_input():
        placement = RayPlacement(address=args.ray or "auto", resources=ray_run.parse_resources(args.ray_resources))
    if max_restarts is not None:
        placement.max_restarts = max_restarts
    return placement


def join_cluster(placement: RayPlacement, cfg: TrainConfig, roles=ROLES, actor_ids=None) -> None:
    """Connect to the cluster and check that it can take the run, before anything is
    written: no Ray, a bad address, nothing there or too few resources is a ``UsageError``."""
    names = ray_run.service_names(cfg, roles, actor_ids)
    with user_input():
        ray = ray_run.connect(placement.address, ray_run.cpus_for_local(placement, names))
        ray_run.check_cluster(ray, placement, names)


def train_mode(args, cfg: TrainConfig | None = None) -> str:
    """``--mode`` (else the config's), where ``--ray ADDRESS`` alone means ``--mode ray``."""
    if args.ray is None:
        if args.ray_resources and args.mode != "ray":
            raise UsageError("--ray-resources places services on a Ray cluster: use it with --mode ray or --ray")
        return args.mode or (cfg.mode if cfg is not None else "inprocess")
    if args.mode == "supervised":
        raise UsageError(f"--ray {args.ray}: use --mode ray (the supervised processes placed on the cluster)")
    return "ray"


# ----------------------------------------------------------------- sage train
def load_config_file(path: str) -> TrainConfig:
    """A saved run config; a missing, truncated or invalid file is a ``UsageError`` naming it."""
    with user_input(f"--config {path}"):
        return read_config(path)


def config_from_args(args) -> TrainConfig:
    """The resolved run config of ``sage train``; bad values are a ``UsageError``."""
    cfg = load_config_file(args.config) if args.config else TrainConfig()
    with user_input():
        return _apply_args(cfg, args)


def _apply_args(cfg: TrainConfig, args) -> TrainConfig:
    """What the user typed, onto ``cfg`` (the defaults, or a loaded ``--config``): only
    given flags and ``--set`` items change it, so a saved config runs exactly as saved."""
    apply_config_flags(cfg, args, TRAIN_FLAGS)
    if args.minutes is not None and args.updates is None:
        cfg.updates = UNLIMITED_UPDATES   # a wall-clock budget alone: train until the minutes are spent
    if args.mode is not None:
        # Ray places the same processes as the supervisor: the run config's mode stays "supervised"
        cfg.mode = "supervised" if train_mode(args) == "ray" else args.mode
    elif args.ray is not None:
        cfg.mode = "supervised"
    if args.metrics_port is not None:
        cfg.ports.inprocess = args.metrics_port
    if args.human_slot is not None:
        cfg.set("env.human_slot", args.human_slot)
    for item in args.set:
        apply_override(cfg, item)
    if cfg.mode == "supervised":
        cfg.actor.exit_on_unhealthy = True  # let the supervisor see and restart it
    return cfg.resolve()


def apply_override(cfg: TrainConfig, item: str) -> None:
    """``SECTION.KEY=VALUE`` onto the config (``env.KEY``, ``algo.KEY``, ``actor.KEY``, ...,
    ``train.KEY`` for a top-level field). The value is parsed as JSON (else taken as a
    string) and must have the field's type; a bad item is a ``SystemExit`` with a one-line
    message naming it."""
    if "=" not in item or "." not in item.split("=", 1)[0]:
        raise SystemExit(f"--set expects SECTION.KEY=VALUE, got {item!r}")
    path, raw = item.split("=", 1)
    try:
        cfg.set_text(path, raw)
    except ValueError as exc:
        raise SystemExit(f"--set {path}={raw}: {one_line(exc)}") from None


def final_eval(cfg: TrainConfig, params: dict) -> dict:
    return evaluate_policy(params, cfg.env_config(), cfg.eval_episodes, seed=FINAL_EVAL_SEED + cfg.seed,
                           shielded=method_spec(cfg.method).shielded, max_steps=cfg.eval_max_steps or None)


def final_evals(cfg: TrainConfig, params: dict, version) -> tuple[dict, list[dict]]:
    """The final evaluation: of the final parameters alone (``eval_checkpoints`` 1), or of
    each of the last ``eval_checkpoints`` checkpoints on the same held-out episodes, with
    their mean as the run's figure. Returns (the evaluation reported, one record per
    evaluated checkpoint: version, its evaluation and the tree parameters evaluated)."""
    evaluated = [(version, params)]
    if cfg.eval_checkpoints > 1:
        evaluated = last_checkpoint_params(RunDir(cfg.run_dir).checkpoints, cfg.eval_checkpoints) or evaluated
    records = [{"version": v, "eval": final_eval(cfg, p), "params": p} for v, p in evaluated]
    if len(records) == 1:
        return records[0]["eval"], records
    return mean_eval([r["eval"] for r in records]), records


def last_checkpoint_params(directory: Path, n: int) -> list[tuple[int, dict]]:
    """(version, tree parameters) of the newest ``n`` checkpoints that load, oldest first."""
    return [(int(ck["version"]), policy_params_from_checkpoint(ck)) for ck in load_newest(directory, n)]


def mean_eval(evals: list[dict]) -> dict:
    """The mean of several evaluations' numbers (per key; lists and maps of the first are kept)."""
    out = dict(evals[0])
    for key, value in evals[0].items():
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            values = [e.get(key) for e in evals if isinstance(e.get(key), (int, float))]
            out[key] = float(np.mean(values)) if values else value
    out["episodes_finished"] = int(sum(e.get("episodes_finished", 0) for e in evals))
    out["checkpoints"] = len(evals)
    return out


def cmd_train(args) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cfg = config_from_args(args)
    mode = train_mode(args, cfg)
    track = tracking_config(args)
    placement = ray_placement(args) if mode == "ray" else None
    code, summary = train_run(cfg, mode, progress=not args.quiet, placement=placement, track=track)
    if summary is None:
        return code
    print(json.dumps({"run_dir": str(cfg.run_dir), "version": summary.get("version"),
                      "updates": summary.get("updates")}))
    return code


def train_run(cfg: TrainConfig, mode: str = "inprocess", progress: bool = True,
              placement: RayPlacement | None = None, track: TrackingConfig | None = None) -> tuple[int, dict | None]:
    """Train the resolved ``cfg`` (``sage train``'s work, also ``sage.api.train``'s): write the
    run directory, run the services where ``mode`` says, evaluate and write ``summary.json``.
    Returns (exit code, summary; None when nothing was trained)."""
    run = RunDir(cfg.run_dir)
    clash = _resume_clash(run, cfg)
    if clash:
        print(f"sage train: {run.root} holds a run of {clash}; the learner would resume its checkpoints. "
              "Use another --run-dir or --run-id (or the run's own config to resume it).", file=sys.stderr)
        return 2, None
    if placement is not None:
        join_cluster(placement, cfg)
    cfg_path = save_run_config(cfg, run)
    print(f"run {cfg.run_id}: {cfg.method} on {cfg.scenario}, {cfg.actors} actor(s) x {cfg.envs_per_actor} envs, "
          f"mode {mode}, run dir {run.root}", file=sys.stderr)
    resuming = resume_note(cfg, run)
    if resuming:
        print(resuming, file=sys.stderr)
    if cfg.tensorboard:   # the learner writes event files when tensorboardX imports
        print(f"tensorboard: events in {run.tensorboard}" if tensorboard_available() else
              "tensorboard: off (pip install 'sage-transport[tensorboard]' for event files)", file=sys.stderr)
    tracking, summary = start_tracking(track, cfg, run), None
    try:
        if mode in ("supervised", "ray"):
            code = int(run_supervised(str(cfg_path)) or 0) if mode == "supervised" else \
                run_ray(cfg_path, placement)
            if code:
                return code, None
            summary, params = supervised_summary(run, mode)
        else:
            out = run_inprocess(cfg, progress=progress)
            code = out.pop("exit_code")
            if code:   # a signal stopped it: nothing to evaluate, as in the process placements
                return code, None
            params = out.pop("params")
            out.pop("status", None)
            summary = {"mode": "inprocess", **out}
        if track is not None:
            summary["tracking"] = {"wandb": {"project": track.project, "run": cfg.run_id,
                                             "dir": tracking[0].run.dir}}
        write_summary(cfg, run, summary, params)
    finally:
        stop_tracking(tracking, summary)
    return 0, summary


def resume_note(cfg: TrainConfig, run: RunDir) -> str | None:
    """``resuming run X from checkpoint version V (update U of N)`` when the learner
    will resume a checkpoint of this run directory; None for a fresh run."""
    if not cfg.resume:
        return None
    ck = load_latest(run.checkpoints)
    if not isinstance(ck, dict) or not {"version", "updates", "env_steps"} <= set(ck):
        return None   # nothing the learner can resume (it says why itself)
    budget = f" of {cfg.updates}" if cfg.updates < UNLIMITED_UPDATES else ""
    return (f"resuming run {cfg.run_id} from checkpoint version {int(ck['version'])} "
            f"(update {int(ck['updates'])}{budget}, {int(ck['env_steps'])} env steps) in {run.checkpoints}")


def supervised_summary(run: RunDir, mode: str) -> tuple[dict, dict | None]:
    """(summary, newest tree params) of a run whose learner ran in another process:
    its newest checkpoint and its last metrics row."""
    try:
        _, params, version = load_run(run.root)
    except FileNotFoundError:
        params, version = None, None
    return {"mode": mode, "version": version, **last_progress(run)}, params


def write_summary(cfg: TrainConfig, run: RunDir, summary: dict, params: dict | None) -> dict:
    """The final deployment evaluation (``cfg.eval_episodes`` > 0; ``final_evals``) into
    ``summary``, the evaluated tree parameters beside it, ``summary.json`` written atomically."""
    if cfg.eval_episodes > 0 and params is not None:
        summary["eval"], evaluated = final_evals(cfg, params, summary.get("version"))
        if len(evaluated) > 1:
            summary["eval_by_checkpoint"] = [{"version": r["version"], **r["eval"]} for r in evaluated]
        save_evaluated_params(run, evaluated)
        e = summary["eval"]
        print(f"eval ({e['episodes_finished']} episodes on {len(evaluated)} checkpoint(s), "
              f"{'shielded' if e['shielded'] else 'unshielded'}): "
              f"SR {e['success_rate']:.2f}  return {e['return_mean']:.2f}  col/1k {e['col_per_1k']:.2f}  "
              f"intervention {e['intervention_rate']:.2f}", file=sys.stderr)
    atomic_write_text(run.summary, json.dumps(summary, indent=2, default=_num) + "\n")
    return summary


def save_evaluated_params(run: RunDir, evaluated: list[dict]) -> Path:
    """The tree parameters the final evaluation ran, one group per checkpoint version, as a
    compressed numpy archive (data only: ``numpy.load(allow_pickle=False)`` reads it), so a
    table resting on this run can be re-evaluated without the checkpoints."""
    arrays = {f"v{r['version']}/{k}": np.asarray(v) for r in evaluated for k, v in r["params"].items()}
    tmp = run.evaluated_params.with_name(run.evaluated_params.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    os.replace(tmp, run.evaluated_params)
    return run.evaluated_params


def run_ray(cfg_path: Path, placement: RayPlacement, **kw) -> int:
    """``run_on_ray`` with its one-line outcomes: the cluster refusing the run is a
    ``UsageError``, a router that never came up exit code 1."""
    try:
        return run_on_ray(cfg_path, placement=placement, **kw)
    except ClusterError as exc:
        raise UsageError(str(exc)) from None
    except RuntimeError as exc:   # e.g. the local router never came up
        print(f"ray: {exc}", file=sys.stderr)
        return EXIT_GAVE_UP


def save_run_config(cfg: TrainConfig, run: RunDir) -> Path:
    """``cfg`` into the run directory; a run dir that cannot be one is a ``UsageError``."""
    if run.root.exists() and not run.root.is_dir():
        raise UsageError(f"run dir {run.root} exists and is not a directory")
    with user_input(f"run dir {run.root}"):
        return cfg.save(run.config)


def _resume_clash(run: RunDir, cfg: TrainConfig) -> str | None:
    """What an existing run directory holds when it cannot be resumed by ``cfg``."""
    if run.root.exists() and not run.root.is_dir():
        raise UsageError(f"run dir {run.root} exists and is not a directory")
    if not run.config.exists():
        return None
    try:
        prev = json.loads(run.config.read_text())
    except (ValueError, OSError):   # not JSON, not text, not readable
        return "an unreadable config.json"
    if not isinstance(prev, dict):
        return "an unreadable config.json"
    if (prev.get("method"), prev.get("scenario")) != (cfg.method, cfg.scenario):
        return f"method {prev.get('method')!r} on {prev.get('scenario')!r}"
    # what the checkpoints were trained under: a resume may change the budget and the
    # placement, not what is being learned
    now = json.loads(cfg.to_json())
    for key in ("seed", "env", "algo"):
        if prev.get(key) != now[key]:
            diff = _first_difference(prev.get(key), now[key], key)
            return f"another {key} config ({diff})"
    return None


def _first_difference(a, b, path: str) -> str:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if a.get(k) != b.get(k):
                return _first_difference(a.get(k), b.get(k), f"{path}.{k}")
    return f"{path} {a!r} there, {b!r} now"


def _num(o):
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)


# ----------------------------------------------------------------- sage up
def add_up_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=None, help="run config JSON (services/config.py); default: a fresh one")
    p.add_argument("--actors", type=positive_int, default=None,
                   help=f"number of actors in the run (default: config's value, or cores-1 = {default_actor_count()} "
                        "for a fresh config)")
    p.add_argument("--shields", type=positive_int, default=None,
                   help="shield shards, each its own process; actor i asks shard i %% shields (default: config's)")
    p.add_argument("--roles", default=",".join(ROLES), help="which services this host runs (default: all)")
    p.add_argument("--actor-ids", default=None, help="actor ids this host runs, e.g. 2-3 (default: all)")
    p.add_argument("--connect", action="append", default=None,
                   help="Zenoh router endpoint, e.g. tcp/10.0.0.1:7447 (repeatable; default: start a local router)")
    p.add_argument("--metrics-base", type=port, default=None,
                   help="Prometheus ports: base learner, base+1+k shield shard k, base+10+i actor i (e.g. 9400; 0 = off)")
    p.add_argument("--restart-budget", type=nonneg_int, default=SupervisorConfig().restart_budget,
                   help="restarts of one service allowed within the supervisor's window before it gives up "
                        "(raise it for chaos runs, actor.chaos_crash_prob); with --ray: Ray's max_restarts "
                        "per service over the whole run")
    add_ray_arguments(p, "the router, shields, learner and actors of this run as Ray actors")
    add_config_flags(p.add_argument_group("the run's config (over --config, or a fresh one)"), UP_FLAGS)


def up_config_from_args(args) -> Path:
    """Write the run config the supervisor will use and return its path."""
    cfg = up_config(args)
    return save_run_config(cfg, RunDir(cfg.run_dir))


def up_config(args) -> TrainConfig:
    """The resolved run config of ``sage up`` (nothing written); bad values are a ``UsageError``."""
    cfg = load_config_file(args.config) if args.config else TrainConfig(actors=default_actor_count())
    with user_input():
        return _apply_up_args(cfg, args)


def _apply_up_args(cfg: TrainConfig, args) -> TrainConfig:
    apply_config_flags(cfg, args, ("actors", "shields") + UP_FLAGS)
    if args.connect:
        cfg.transport.connect = list(args.connect)
        cfg.transport.mode = "client"  # reach the other services through the router
    if args.metrics_base is not None:
        base = args.metrics_base
        cfg.ports.learner = base + METRICS_OFFSETS["learner"] if base else 0
        cfg.ports.shield = base + METRICS_OFFSETS["shield"] if base else 0
        cfg.ports.actor_base = base + METRICS_OFFSETS["actor_base"] if base else 0
    cfg.mode = "supervised"
    return cfg.resolve()


def parse_roles(text: str) -> list[str]:
    roles = [r.strip() for r in text.split(",") if r.strip()]
    bad = [r for r in roles if r not in ROLES]
    if bad or not roles:
        what = f"unknown roles {bad}" if bad else "no roles"
        raise UsageError(f"--roles {text!r}: {what}; choose from {', '.join(ROLES)}")
    return roles


def cmd_up(args) -> int:
    # everything the user gave is checked before anything is written or started
    roles = parse_roles(args.roles)
    cfg = up_config(args)
    ids = None
    if args.actor_ids:
        with user_input("--actor-ids"):
            ids = parse_ids(args.actor_ids)
        if max(ids) >= cfg.actors:
            raise UsageError(f"--actor-ids {args.actor_ids}: the run has {cfg.actors} actor(s), "
                             f"ids 0..{cfg.actors - 1}")
    if args.ray_resources and args.ray is None:
        raise UsageError("--ray-resources places services on a Ray cluster: use it with --ray ADDRESS")
    run = RunDir(cfg.run_dir)
    if args.ray is not None:
        placement = ray_placement(args, max_restarts=args.restart_budget)
        join_cluster(placement, cfg, roles, ids)
        path = save_run_config(cfg, run)
        _say_resuming(cfg, run, roles)
        code = run_ray(path, placement, roles=roles, actor_ids=ids)
    else:
        path = save_run_config(cfg, run)
        _say_resuming(cfg, run, roles)
        try:
            code = run_supervised(path, roles=roles, actor_ids=ids,
                                  supervisor=SupervisorConfig(restart_budget=args.restart_budget))
        except RuntimeError as exc:  # e.g. the local router never came up
            print(f"sage up: {exc}", file=sys.stderr)
            return EXIT_GAVE_UP
    if code == 0 and "learner" in roles:
        # the host of the learner writes what `sage train` writes: summary.json with the final evaluation
        summary, params = supervised_summary(run, "ray" if args.ray is not None else "supervised")
        write_summary(cfg, run, summary, params)
    return code


def _say_resuming(cfg: TrainConfig, run: RunDir, roles) -> None:
    note = resume_note(cfg, run) if "learner" in roles else None
    if note:
        print(note, file=sys.stderr)
