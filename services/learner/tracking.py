"""Experiment tracking where users already look: TensorBoard event files under
``<run_dir>/tb/`` (written by the learner's ``MetricsLog``) and, optionally,
Weights & Biases (``sage train --track``; the optional ``wandb`` extra).

Every per-update metric is one scalar, tagged ``<section>/<name>`` with the
sections ``train/`` (losses, returns, episode outcomes), ``deploy/`` (the
learner's deterministic deployment probe), ``mechanism/`` (the shield, SAIL
and TALO diagnostics) and ``system/`` (timings, staleness, chunk counts), and
plotted against env steps (the row's ``env_steps``; the update number is the
scalar ``system/update``). The resolved run config is written once per event
file as text (``config/text_summary``) and as TensorBoard HParams, and is the
W&B run's config.
"""
from __future__ import annotations

import json
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable


SECTIONS = ("train", "deploy", "mechanism", "system")
# the mechanism metrics of Sec. IV (shield correction, proposal violation, SAIL, TALO)
_MECHANISM = ("w_gap", "cos_ind_team", "talo_", "proposal_violation", "correction", "exec_minus_prop",
              "sail_residual", "kappa", "tau", "happo_factor", "logratio_at_start", "actor_step_norm",
              "intervention_rate", "unfiltered_steps")
_SYSTEM = ("update", "version", "env_steps", "time_s", "update_s", "update_cpu_s", "progress", "batch_T",
           "batch_K", "lag_max", "chunks_", "deploy_probe_s", "queue")
# the hparams metrics TensorBoard's HParams view lists beside the config
HPARAM_METRICS = ("train/reward_mean", "train/ep_success_mean", "deploy/deploy_sr", "mechanism/correction_mean")


def section(key: str) -> str:
    """The section of a metrics key (one of ``SECTIONS``)."""
    if key == "deploy_probe_s":
        return "system"                       # the probe's cost, not its outcome
    if key.startswith("deploy_"):
        return "deploy"
    if any(key == p or (p.endswith("_") and key.startswith(p)) or key.startswith(p + "_") for p in _SYSTEM):
        return "system"
    if any(key == p or (p.endswith("_") and key.startswith(p)) or key.startswith(p + "_") for p in _MECHANISM):
        return "mechanism"
    return "train"


def scalars_of(row: dict) -> dict[str, float]:
    """``{"<section>/<key>": value}`` of a metrics row's numeric entries."""
    return {f"{section(k)}/{k}": float(v) for k, v in row.items()
            if isinstance(v, (int, float)) and not isinstance(v, bool)}


def x_of(row: dict) -> int:
    """The x-axis step of a metrics row: its env steps (its update without them)."""
    return int(row["env_steps"] if row.get("env_steps") is not None else row["update"])


def flat_config(config: dict, prefix: str = "") -> dict[str, float | str | bool]:
    """A nested config as ``{"algo/actor_lr": 0.0003, ...}`` of numbers, strings and
    bools (lists and None as their JSON text), what HParams and W&B can show."""
    out: dict[str, float | str | bool] = {}
    for k, v in config.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flat_config(v, name + "/"))
        elif isinstance(v, (bool, int, float, str)):
            out[name] = v
        else:
            out[name] = json.dumps(v)
    return out


def tensorboard_available() -> bool:
    """Whether tensorboardX (the optional ``tensorboard`` extra) can be imported."""
    try:
        import tensorboardX  # noqa: F401
    except ImportError:
        return False
    return True


class EventFile:
    """One TensorBoard event file in ``logdir``, written synchronously through
    tensorboardX's TFRecord writer (no background thread: ``scalars`` is on disk
    when it returns). TensorBoard reads every event file of a directory, so a
    resumed learner opens a new file beside the old ones; ``purge_step`` (an env
    step) writes the session-start marker that makes TensorBoard drop the earlier
    files' events at steps >= it (the updates the restart rolled back).
    ``config``: the resolved run config, written as text and HParams."""

    def __init__(self, logdir: str | Path, suffix: str = "", purge_step: int | None = None,
                 config: dict | None = None):
        from tensorboardX import summary as tbx_summary
        from tensorboardX.proto.event_pb2 import Event, SessionLog
        from tensorboardX.proto.summary_pb2 import Summary
        from tensorboardX.record_writer import RecordWriter

        self._Event, self._Summary, self._tbx = Event, Summary, tbx_summary
        logdir = Path(logdir)
        logdir.mkdir(parents=True, exist_ok=True)
        self.path = logdir / (f"events.out.tfevents.{int(time.time()):010d}.{socket.gethostname()}"
                              + (f".{suffix}" if suffix else ""))
        self._writer = RecordWriter(str(self.path))
        self._write(Event(wall_time=time.time(), file_version="brain.Event:2"))
        if purge_step is not None:
            self._write(Event(wall_time=time.time(), step=int(purge_step),
                              session_log=SessionLog(status=SessionLog.START)))
        self._hparams = config is not None
        if config is not None:
            self._summary(0, tbx_summary.text("config", "```\n" + json.dumps(config, indent=2) + "\n```"))
            exp, start, _ = tbx_summary.hparams(flat_config(config), {m: 0.0 for m in HPARAM_METRICS})
            self._summary(0, exp)
            self._summary(0, start)
        self._writer.flush()

    def _write(self, event) -> None:
        self._writer.write(event.SerializeToString())

    def _summary(self, step: int, summary) -> None:
        self._write(self._Event(wall_time=time.time(), step=int(step), summary=summary))

    def scalars(self, step: int, values: dict[str, float]) -> None:
        """One event at ``step`` holding a scalar per entry, flushed."""
        summary = self._Summary(value=[self._Summary.Value(tag=k, simple_value=float(v)) for k, v in values.items()])
        self._summary(step, summary)
        self._writer.flush()

    def row(self, row: dict) -> None:
        """A metrics row: its numeric entries by section, at its env steps."""
        self.scalars(x_of(row), scalars_of(row))

    def close(self) -> None:
        if self._writer is not None:
            if self._hparams:
                *_, end = self._tbx.hparams({}, {})
                self._summary(0, end)
            self._writer.close()
            self._writer = None


# ----------------------------------------------------------------- Weights & Biases
WANDB_HINT = "pip install 'sage-transport[wandb]'"


@dataclass
class TrackingConfig:
    """``sage train --track``: log the run to Weights & Biases (the learner's metrics
    rows as they are written, the resolved config, the final evaluation). W&B's own
    environment variables apply: ``WANDB_MODE=offline`` logs to ``wandb/`` under
    ``dir`` with no network (``wandb sync`` uploads it later)."""
    project: str = "sage-transport"
    entity: str | None = None
    group: str | None = None          # e.g. a suite's name
    dir: str | None = None            # default: the run directory
    poll_s: float = 1.0               # how often the metrics file is read for new rows


def wandb_available() -> bool:
    try:
        import wandb  # noqa: F401
    except ImportError:
        return False
    return True


class WandbRun:
    """One W&B run of a SAGE run: ``log(row)`` per metrics row (the same
    ``<section>/<key>`` names as TensorBoard, ``env_steps`` as the step metric),
    ``finish(summary)`` with the final evaluation as the run summary."""

    def __init__(self, cfg: TrackingConfig, run_id: str, run_dir: str | Path, config: dict):
        import wandb

        self._wandb = wandb
        self.run = wandb.init(project=cfg.project, entity=cfg.entity, group=cfg.group, name=run_id, id=run_id,
                              dir=str(cfg.dir or run_dir), config=config, resume="allow", reinit="create_new",
                              settings=wandb.Settings(quiet=True, save_code=False))
        # every metric against env steps (CleanRL's global_step)
        self.run.define_metric("system/env_steps")
        self.run.define_metric("*", step_metric="system/env_steps")
        self.last_update = 0

    def log(self, row: dict) -> None:
        """A metrics row, once: rows of an update already logged (a resumed learner
        redoing rolled-back updates) are skipped, W&B steps only go forward."""
        update = int(row.get("update", 0))
        if update <= self.last_update:
            return
        self.last_update = update
        values = scalars_of(row)
        values["system/env_steps"] = float(x_of(row))
        self.run.log(values)

    def finish(self, summary: dict | None = None) -> None:
        """The run's outcome (``summary.json``'s updates, version, env steps and final
        evaluation) as the W&B summary ``final/...``, then the run is closed."""
        kept = {k: v for k, v in (summary or {}).items() if k in ("updates", "version", "env_steps", "eval")}
        for k, v in flat_config(kept).items():
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                self.run.summary[f"final/{k}"] = v
        self.run.finish()


class MetricsTail:
    """Reads ``metrics.jsonl`` every ``poll_s`` seconds on a thread and hands each
    new complete line's row to ``sink`` (the learner may run in this process or in
    another: the file is what both write). A file replaced by a resumed learner
    (rolled-back rows moved out) is read again from its start; ``stop`` reads it a
    last time."""

    def __init__(self, path: str | Path, sink: Callable[[dict], None], poll_s: float = 1.0):
        self.path, self.sink, self.poll_s = Path(path), sink, poll_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="metrics-tail", daemon=True)
        self._inode, self._offset = None, 0
        self.rows = 0                          # rows handed to the sink

    def start(self) -> "MetricsTail":
        self._thread.start()
        return self

    def poll(self) -> None:
        try:
            st = self.path.stat()
        except FileNotFoundError:
            return
        if st.st_ino != self._inode or st.st_size < self._offset:
            self._inode, self._offset = st.st_ino, 0
        with open(self.path, "rb") as f:
            f.seek(self._offset)
            data = f.read()
        end = data.rfind(b"\n") + 1          # complete lines only: the learner may be mid-write
        for line in data[:end].splitlines():
            try:
                row = json.loads(line)
            except ValueError:
                continue
            if isinstance(row, dict):
                self.sink(row)
                self.rows += 1
        self._offset += end

    def _loop(self) -> None:
        while not self._stop.wait(self.poll_s):
            self.poll()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        self.poll()
