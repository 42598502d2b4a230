"""Per-episode transport metrics and their aggregation (paper Sec. IV-A).

An episode record (built by ``BatchEnv`` when an episode ends) holds:

* ``success`` (bool), ``drop`` (bool), ``return`` (sum of shared rewards), ``steps``;
* ``collision_steps`` and ``col_per_1k`` = 1000 * collision_steps / steps (control
  steps with any carrier or payload contact with a wall);
* ``margin_violation_steps`` and ``margin_col_per_1k`` = 1000 * margin_violation_steps
  / steps: control steps after which some true barrier of the shield's own
  specification is below ``-EnvConfig.margin_violation_tol`` (5 mm; common/env/safety.py
  ``spec_barrier_min``: carrier disc + margin and payload points + margin vs walls, plus
  the formation band under the ``"grasp"`` row profile), i.e. the shield's safe set was
  left by a measurable amount, contact or not (:func:`margin_violation`);
* ``truncated`` (bool: the time limit ended it, neither success nor drop) and ``deadlock``
  (bool: truncated with the payload still for the last ``EnvConfig.deadlock_window_s``);
  a truncated episode that is not a deadlock is a timeout. success, drop and truncated
  partition the episodes;
* ``completion_time`` (s, successful episodes only, else NaN);
* ``tilt`` (mean payload tilt from vertical, deg), ``heading_error`` (mean |payload yaw
  - route heading|, rad), ``height_error`` (mean |payload height - carry height|, m);
* ``min_clearance`` (min over the episode of the formation's distance to walls, m);
* ``progress_per_step`` (route progress gained per step), ``final_progress``.
"""
from __future__ import annotations

import math

import numpy as np

EPISODE_KEYS = ("success", "drop", "truncated", "deadlock", "return", "steps", "collision_steps", "col_per_1k",
                "margin_violation_steps", "margin_col_per_1k", "completion_time", "tilt", "heading_error", "height_error", "min_clearance", "progress_per_step", "final_progress")

_AGG = {  # aggregate name -> episode key
    "success_rate": "success", "return_mean": "return", "col_per_1k": "col_per_1k",
    "margin_col_per_1k": "margin_col_per_1k", "drop_rate": "drop",
    "completion_time": "completion_time", "tilt": "tilt", "heading_error": "heading_error",
    "height_error": "height_error", "min_clearance": "min_clearance", "progress_per_step": "progress_per_step",
}


_OPTIONAL = ("margin_col_per_1k",)   # episode keys that records written before they existed lack


def margin_violation(barrier_min, tol: float) -> np.ndarray:
    """Margin violation [K] bool: the smallest true barrier is below ``-tol`` (m)."""
    return np.asarray(barrier_min) < -float(tol)


def _outcomes(episodes: list[dict]) -> dict:
    """``truncation_rate``, ``timeout_rate``, ``deadlock_rate``: shares of the episodes,
    beside ``success_rate`` and ``drop_rate`` (the three partition the episodes). A record
    written before ``truncated`` existed counts as truncated when it is neither a success
    nor a drop (what ended it then); its deadlock is unknown, and the deadlock and timeout
    rates are NaN unless every record has one."""
    truncated = np.array([bool(e.get("truncated", not e["success"] and not e["drop"])) for e in episodes])
    out = {"truncation_rate": float(truncated.mean())}
    if all("deadlock" in e for e in episodes):
        deadlock = np.array([bool(e["deadlock"]) for e in episodes]) & truncated
        out["deadlock_rate"], out["timeout_rate"] = float(deadlock.mean()), float((truncated & ~deadlock).mean())
    else:
        out["deadlock_rate"] = out["timeout_rate"] = math.nan
    return out


def aggregate(episodes: list[dict]) -> dict:
    """Means and standard deviations over episodes: ``{name: mean, name + "_std": std, "episodes": n}``.

    ``col_per_1k`` and ``margin_col_per_1k`` are also given pooled over all steps
    (``col_per_1k_pooled``, ``margin_col_per_1k_pooled``);
    ``completion_time`` averages successful episodes only (NaN if none); an episode record
    without ``margin_col_per_1k`` (written before it existed) is skipped like NaN. How the
    episodes ended: ``success_rate``, ``drop_rate`` and ``truncation_rate`` (= ``timeout_rate``
    + ``deadlock_rate``), reported apart.
    """
    out: dict = {"episodes": len(episodes)}
    if not episodes:
        for name in _AGG:
            out[name], out[name + "_std"] = math.nan, math.nan
        out["col_per_1k_pooled"] = out["margin_col_per_1k_pooled"] = math.nan
        out["truncation_rate"] = out["timeout_rate"] = out["deadlock_rate"] = math.nan
        return out
    for name, key in _AGG.items():
        vals = np.array([float(e[key] if key in e or key not in _OPTIONAL else math.nan) for e in episodes],
                        dtype=np.float64)
        vals = vals[~np.isnan(vals)]
        out[name] = float(vals.mean()) if len(vals) else math.nan
        out[name + "_std"] = float(vals.std()) if len(vals) else math.nan
    steps = sum(int(e["steps"]) for e in episodes)
    out["col_per_1k_pooled"] = 1000.0 * sum(int(e["collision_steps"]) for e in episodes) / max(steps, 1)
    marked = [e for e in episodes if "margin_violation_steps" in e]   # records older than the margin count lack it
    out["margin_col_per_1k_pooled"] = (1000.0 * sum(int(e["margin_violation_steps"]) for e in marked)
                                       / max(sum(int(e["steps"]) for e in marked), 1) if marked else math.nan)
    out.update(_outcomes(episodes))
    return out
