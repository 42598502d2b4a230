"""``sage train``: the main job (in-process services by default)."""
from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

from services.config import METHODS, TrainConfig


def register(commands, bench) -> None:
    d = TrainConfig()
    p = commands.add_parser("train", help="train a method with actor/shield/learner services")
    p.add_argument("--scenario", default=d.scenario)
    p.add_argument("--method", default=d.method, choices=METHODS)
    p.add_argument("--updates", type=int, default=None,
                   help=f"learner updates (budget; default {d.updates}, or unlimited when --minutes is given)")
    p.add_argument("--minutes", type=float, default=d.minutes, help="wall-clock budget (whichever first)")
    p.add_argument("--actors", type=int, default=d.actors)
    p.add_argument("--envs-per-actor", type=int, default=d.envs_per_actor)
    p.add_argument("--chunk-len", type=int, default=d.chunk_len)
    p.add_argument("--max-lag", type=int, default=d.max_lag)
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--run-id", default="")
    p.add_argument("--run-dir", default="")
    p.add_argument("--mode", default=d.mode, choices=("inprocess", "supervised"))
    p.add_argument("--eval-episodes", type=int, default=d.eval_episodes)
    p.add_argument("--metrics-port", type=int, default=0, help="Prometheus port (in-process registry); 0 = off")
    p.add_argument("--config", default=None, help="start from a saved config JSON (flags override)")
    p.add_argument("--human-slot", type=int, default=None, choices=(0, 1, 2),
                   help="put the scripted human partner in this carrier slot (exogenous, no tree)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a config field, e.g. --set algo.actor_lr=1e-3 --set env.max_steps=400 "
                        "--set shield.window_s=0.001 --set train.deploy_probe_every=10 (value parsed as JSON, else string)")
    p.add_argument("--quiet", action="store_true", help="no live progress line")
    p.set_defaults(func=cmd_train)


def config_from_args(args) -> TrainConfig:
    cfg = TrainConfig.load(args.config) if args.config else TrainConfig()
    if args.updates is not None:
        updates = args.updates
    elif args.minutes:
        updates = 10**9  # a wall-clock budget alone: train until the minutes are spent
    else:
        updates = cfg.updates
    cfg.scenario, cfg.method, cfg.updates, cfg.minutes = args.scenario, args.method, updates, args.minutes
    cfg.actors, cfg.envs_per_actor, cfg.chunk_len = args.actors, args.envs_per_actor, args.chunk_len
    cfg.max_lag, cfg.seed, cfg.mode, cfg.eval_episodes = args.max_lag, args.seed, args.mode, args.eval_episodes
    cfg.ports.inprocess = args.metrics_port
    if args.human_slot is not None:
        cfg.env = {**cfg.env, "human_slot": args.human_slot}
    for item in args.set:
        apply_override(cfg, item)
    if args.run_id:
        cfg.run_id = args.run_id
    if args.run_dir:
        cfg.run_dir = args.run_dir
    if cfg.mode == "supervised":
        cfg.actor.exit_on_unhealthy = True  # let the supervisor see and restart it
    return cfg.resolve()


def apply_override(cfg: TrainConfig, item: str) -> None:
    """``SECTION.KEY=VALUE`` onto the config (env/algo dicts, a nested dataclass, or
    ``train.KEY`` for a plain top-level TrainConfig field)."""
    import dataclasses

    if "=" not in item or "." not in item.split("=", 1)[0]:
        raise SystemExit(f"--set expects SECTION.KEY=VALUE, got {item!r}")
    path, raw = item.split("=", 1)
    section, key = path.split(".", 1)
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    if section in ("env", "algo"):
        setattr(cfg, section, {**getattr(cfg, section), key: value})
        return
    if section == "train":
        plain = {f.name for f in dataclasses.fields(cfg)
                 if not dataclasses.is_dataclass(getattr(cfg, f.name)) and f.name not in ("env", "algo")}
        if key not in plain:
            raise SystemExit(f"--set: unknown config field {path!r} (train.* takes {', '.join(sorted(plain))})")
        setattr(cfg, key, value)
        return
    target = getattr(cfg, section, None)
    if not dataclasses.is_dataclass(target) or key not in {f.name for f in dataclasses.fields(target)}:
        raise SystemExit(f"--set: unknown config field {path!r}")
    setattr(target, key, value)


def final_eval(cfg: TrainConfig, params: dict) -> dict:
    from common.evaluation import evaluate_policy
    from services.config import FINAL_EVAL_SEED

    return evaluate_policy(params, cfg.env_config(), cfg.eval_episodes, seed=FINAL_EVAL_SEED + cfg.seed,
                           shielded=cfg.method != "happo", max_steps=cfg.eval_max_steps or None)


def cmd_train(args) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cfg = config_from_args(args)
    run = Path(cfg.run_dir)
    clash = _resume_clash(run, cfg)
    if clash:
        print(f"sage train: {run} holds a run of {clash}; the learner would resume its checkpoints. "
              "Use another --run-dir (or the same method and scenario to resume).", file=sys.stderr)
        return 2
    cfg_path = cfg.save(run / "config.json")
    print(f"run {cfg.run_id}: {cfg.method} on {cfg.scenario}, {cfg.actors} actor(s) x {cfg.envs_per_actor} envs, "
          f"mode {cfg.mode}, run dir {run}", file=sys.stderr)
    if cfg.mode == "supervised":
        try:
            from deploy.supervisor import run_supervised
        except ImportError as exc:
            print(f"supervised mode needs deploy/supervisor.py ({exc})", file=sys.stderr)
            return 2
        code = int(run_supervised(str(cfg_path)) or 0)
        if code:
            return code
        from common.checkpoint import load_latest

        ck = load_latest(run / "checkpoints")
        params = _params_from_checkpoint(cfg, ck) if ck else None
        summary = {"mode": "supervised", "version": int(ck["version"]) if ck else None,
                   **_last_progress(run / "metrics.jsonl")}
    else:
        from services.inprocess import run_inprocess

        out = run_inprocess(cfg, progress=not args.quiet)
        params = out.pop("params")
        out.pop("status", None)
        summary = {"mode": "inprocess", **out}
    if cfg.eval_episodes > 0 and params is not None:
        summary["eval"] = final_eval(cfg, params)
        e = summary["eval"]
        print(f"eval ({e['episodes_finished']} episodes, {'shielded' if e['shielded'] else 'unshielded'}): "
              f"SR {e['success_rate']:.2f}  return {e['return_mean']:.2f}  col/1k {e['col_per_1k']:.2f}  "
              f"intervention {e['intervention_rate']:.2f}", file=sys.stderr)
    (run / "summary.json").write_text(json.dumps(summary, indent=2, default=_num) + "\n")
    print(json.dumps({"run_dir": str(run), "version": summary.get("version"),
                      "updates": summary.get("updates")}))
    return 0


def _last_progress(metrics_path: Path) -> dict:
    """Updates and env steps from the learner's last metrics row (the supervised
    learner runs in another process, so its counters reach us through its log)."""
    last = None
    if metrics_path.exists():
        for line in metrics_path.read_text().splitlines():
            try:
                last = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut short by a killed learner
    if not last:
        return {}
    return {"updates": last.get("update"), "env_steps": last.get("env_steps")}


def _resume_clash(run: Path, cfg: TrainConfig) -> str | None:
    """What an existing run directory holds when it cannot be resumed by ``cfg``."""
    old = run / "config.json"
    if not old.exists():
        return None
    try:
        prev = json.loads(old.read_text())
    except json.JSONDecodeError:
        return "an unreadable config.json"
    if (prev.get("method"), prev.get("scenario")) != (cfg.method, cfg.scenario):
        return f"method {prev.get('method')!r} on {prev.get('scenario')!r}"
    return None


def _params_from_checkpoint(cfg: TrainConfig, ck: dict) -> dict:
    from services.learner.service import _default_method

    method = _default_method(cfg)
    method.load_state_dict(ck["method"])
    return method.policy_params()


def _num(o):
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)
