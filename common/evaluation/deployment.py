"""Deterministic deployment: hard trees + exact joint CBF-QP, one loop.

At deployment SAIL, exploration, the critic and TALO are removed (Sec. III-D):
the executed action is Q_CBF(x, a_ST) (Eq. qpshield) of the hard-tree action
a_ST (Eq. hard_tree_policy, ``propose(mode="deploy")``); a human-held block
keeps the human's measured action and is never corrected. Unshielded
evaluation executes a_ST clipped to the action box, which is what the env
executes anyway.

``evaluate_policy`` runs one env per episode (so short episodes are not
over-represented) until every env finished its first episode, and returns
the aggregate metrics; an optional ``recorder`` sees every live step, so
``sage eval --record`` records the very episodes it scores.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from common.env.batch_env import BatchEnv
from common.env.metrics import aggregate
from common.policy.rollout import propose
from common.policy.tree import ValidatedParams
from common.safety_rows import VIOLATION_TOL, SafetyRows
from common.shield.qp import STATUS_INFEASIBLE, shield_actions



class DeploymentRecorder(Protocol):
    """Receives the deployment loop's steps (``common.audit.recording.Recorder``)."""

    def on_step(self, env: BatchEnv, out: dict, rows: SafetyRows, decision: dict, a_exec: np.ndarray,
                active: np.ndarray, live: np.ndarray) -> None: ...

    def on_episode(self, k: int, metrics: dict) -> None: ...


def deployment_step(params: dict, out: dict, shielded: bool, backend: str = "default"):
    """The deployed decision for one env step: (rows, decision, a_exec, qp result or None)."""
    rows = SafetyRows.of(out)
    decision = propose(params, out["obs"], rows, out["human_action"], rng=None, mode="deploy")
    if shielded:
        res = shield_actions(decision["a_st"], rows, backend=backend)   # Eq. (qpshield)
        return rows, decision, res.a_exec, res
    return rows, decision, np.clip(decision["a_st"], -1.0, 1.0), None


def row_kind_slices(env: BatchEnv) -> dict[str, slice]:
    """Row slots of each kind the env's row profile has (common.env.safety ``SafetyConfig.kind_slices``):
    ``[carrier-wall | payload-wall]`` under ``safety_rows="paper"``, ``[... | formation]`` under
    ``"grasp"`` (no ``formation`` key under ``"paper"``: there are no such rows to violate),
    plus ``any_wall`` (carrier-wall and payload-wall together)."""
    kinds = dict(env.safety_cfg.kind_slices)
    kinds["any_wall"] = slice(0, kinds["payload_wall"].stop)
    return kinds


def evaluate_policy(params: dict, env_cfg, episodes: int, seed: int, shielded: bool,
                    max_steps: int | None = None, backend: str = "default",
                    recorder: DeploymentRecorder | None = None, on_step=None) -> dict:
    """Run ``episodes`` deployment episodes; ``common.env.metrics.aggregate`` plus
    shield statistics: ``intervention_rate`` (steps with correction > 1e-6),
    ``correction_mean``, ``infeasible_steps``, ``proposal_violation_rate``
    (share of a_ST violating a row by > 1e-6) and ``proposal_violation_by_kind``
    (the same per row kind of the profile, :func:`row_kind_slices`: carrier-wall,
    payload-wall, formation under ``safety_rows="grasp"`` only, and any_wall), which
    tells obstacle constraints apart from the tight grasp-formation rows.
    Two collision measures come from the episodes (``aggregate``): ``col_per_1k``
    (steps with physical wall contact) and ``margin_col_per_1k`` (steps after which a
    true barrier of the shield's own specification is below ``-margin_violation_tol``,
    5 mm, contact or not), both as the per-episode mean (with ``_std``) and pooled
    (``_pooled``: violation steps / all steps); ``margin_violation_steps`` is the pooled
    count. How the episodes ended, apart: ``success_rate``, ``drop_rate`` and
    ``truncation_rate`` (time limit) = ``timeout_rate`` + ``deadlock_rate`` (the payload
    still for the last ``deadlock_window_s``: e.g. the shield holding the team at a gate).
    ``max_steps`` caps the loop (default: the episode limit + 1, by which every
    episode has ended). ``on_step(finished, step, limit)``, if given, is called
    after every step (progress displays)."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    params = ValidatedParams(params)   # checked once here, not in every step's forward
    env = BatchEnv(env_cfg, episodes, seed=seed, layout_purpose="eval")   # held-out layouts
    out = env.reset()
    first: list[dict | None] = [None] * episodes
    steps = interventions = infeasible = violations = 0
    kinds = row_kind_slices(env)
    kind_violations = dict.fromkeys(kinds, 0)
    corr_sum = 0.0
    limit = max_steps or int(env.max_steps) + 1
    for t in range(limit):
        live = np.array([f is None for f in first])
        if not live.any():
            break
        rows, decision, a_exec, res = deployment_step(params, out, shielded, backend)
        row_viol = (rows.residual(decision["a_st"]) > VIOLATION_TOL)
        violations += int((row_viol.any(axis=1) & live).sum())
        for name, sl in kinds.items():
            kind_violations[name] += int((row_viol[:, sl].any(axis=1) & live).sum())
        if res is not None:
            interventions += int(((res.correction_norm > 1e-6) & live).sum())
            corr_sum += float(res.correction_norm[live].sum())
            infeasible += int(((res.status == STATUS_INFEASIBLE) & live).sum())
            active = res.active
        else:
            active = np.zeros(np.shape(rows.row_mask), dtype=bool)
        if recorder is not None:
            recorder.on_step(env, out, rows, decision, a_exec, active, live)
        steps += int(live.sum())
        out = env.step(a_exec)
        done = np.flatnonzero(out["terminated"] | out["truncated"])
        for k, ep in zip(done, out["episodes"]):  # episodes are listed in env order
            if first[k] is None:
                first[k] = ep
                if recorder is not None:
                    recorder.on_episode(int(k), ep)
        if on_step is not None:
            on_step(sum(f is not None for f in first), t + 1, limit)
    finished = [f for f in first if f is not None]
    result = aggregate(finished)
    result.update({"episodes_requested": episodes, "episodes_finished": len(finished), "shielded": shielded,
                   "steps": steps, "intervention_rate": interventions / max(steps, 1),
                   "correction_mean": corr_sum / max(steps, 1), "infeasible_steps": infeasible,
                   "proposal_violation_rate": violations / max(steps, 1),
                   "proposal_violation_by_kind": {k: v / max(steps, 1) for k, v in kind_violations.items()},
                   "margin_violation_steps": sum(int(e["margin_violation_steps"]) for e in finished),
                   "safety_rows": env.safety_cfg.profile,
                   "seed": seed})
    return result
