"""Deterministic deployment evaluation: hard trees + exact joint CBF-QP.

At deployment SAIL, exploration, the critic and TALO are removed (Sec. III-D):
the executed action is Q_CBF(x, a_ST) (Eq. qpshield) with the hard-tree
action a_ST (Eq. hard_tree_policy); a human-occupied block keeps the human's
measured action. Unshielded evaluation executes a_ST directly.
"""
from __future__ import annotations

import numpy as np


def evaluate_policy(params: dict, env_cfg, episodes: int, seed: int, shielded: bool,
                    max_steps: int | None = None, backend: str = "default") -> dict:
    """Run ``episodes`` episodes (one per env, so short episodes are not
    over-represented) and return ``common.env.metrics.aggregate`` plus shield
    statistics: ``intervention_rate`` (steps with correction > 1e-6),
    ``correction_mean``, ``infeasible_steps``, ``proposal_violation_rate``
    (share of a_ST violating a row by > 1e-6) and ``proposal_violation_by_kind``
    (the same share per row kind: carrier-wall, payload-wall, formation, and
    any_wall for either wall kind), which tells obstacle constraints apart from
    the tight grasp-formation rows."""
    from common.env.batch_env import BatchEnv
    from common.env.metrics import aggregate
    from common.qp import qp_violation, solve_cbf_qp
    from common.tree import team_forward_np

    if episodes < 1:
        raise ValueError("episodes must be >= 1")
    env = BatchEnv(env_cfg, episodes, seed=seed)
    out = env.reset()
    first: list[dict | None] = [None] * episodes
    steps = interventions = infeasible = violations = 0
    # row slots are laid out [carrier-wall | payload-wall | formation] (common.env.safety)
    cb, pb = env.safety_cfg.carrier_budget, env.safety_cfg.payload_budget
    kind_slices = {"carrier_wall": slice(0, cb), "payload_wall": slice(cb, cb + pb),
                   "formation": slice(cb + pb, None)}
    kind_slices["any_wall"] = slice(0, cb + pb)   # obstacle rows of either kind
    kind_violations = dict.fromkeys(kind_slices, 0)
    corr_sum = 0.0
    limit = max_steps or 100_000
    for _ in range(limit):
        a_st, *_ = team_forward_np(params, out["obs"])
        a_st = np.where(out["fixed_mask"], out["human_action"], a_st)
        live = np.array([f is None for f in first])
        viol = qp_violation(a_st, out["C"], out["c"], out["row_mask"]) > 1e-6
        violations += int((viol & live).sum())
        row_viol = (out["c"] - np.einsum("kmd,kd->km", out["C"], a_st) > 1e-6) & out["row_mask"]
        for name, rows in kind_slices.items():
            kind_violations[name] += int((row_viol[:, rows].any(axis=1) & live).sum())
        if shielded:
            res = solve_cbf_qp(a_st, out["C"], out["c"], out["row_mask"], out["fixed_mask"], backend=backend)
            a_exec = res.a_exec
            interventions += int(((res.correction_norm > 1e-6) & live).sum())
            corr_sum += float(res.correction_norm[live].sum())
            infeasible += int(((res.status == 1) & live).sum())
        else:
            a_exec = a_st
        steps += int(live.sum())
        out = env.step(a_exec)
        done = np.flatnonzero(out["terminated"] | out["truncated"])
        for k, ep in zip(done, out["episodes"]):  # episodes are listed in env order
            if first[k] is None:
                first[k] = ep
        if all(f is not None for f in first):
            break
    finished = [f for f in first if f is not None]
    res = aggregate(finished)
    res.update({"episodes_requested": episodes, "episodes_finished": len(finished), "shielded": shielded,
                "steps": steps, "intervention_rate": interventions / max(steps, 1),
                "correction_mean": corr_sum / max(steps, 1), "infeasible_steps": infeasible,
                "proposal_violation_rate": violations / max(steps, 1),
                "proposal_violation_by_kind": {k: v / max(steps, 1) for k, v in kind_violations.items()},
                "seed": seed})
    return res
