"""Actor-side step logic (numpy only; actor processes never import torch).

One control step for K environments, Eq. (action_chain) up to the shield:

    a_ST = team hard-tree forward          (common/policy/tree.py, Eq. hard_tree_policy)
    a_bar = Pi_kappa(x, a_ST)              (common/policy/sail.py, Eq. sail_projection; identity without SAIL)
    a_prop ~ pi(. | a_bar)                 (common/policy/proposal.py; "train" mode)

The exact CBF-QP (a_prop -> a_exec) runs in the shield service, not here.

Human partner: where `fixed_mask` is True (whole 3-column carrier blocks) the
measured `human_action` replaces a_st, a_bar and a_prop in that block, SAIL
treats it as a fixed exogenous block (only the robot blocks move), and the
block's log-prob is 0 (the human has no tree and no proposal density).

Deploy mode is deterministic: a_prop = a_st (SAIL and sampling are training-only)
and logp = 0 (log-probability 1 of the deterministic choice).
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from common.policy import proposal_kernels
from common.policy.proposal import ProposalConfig, proposal_sample_np
from common.policy.sail import SailConfig, sail_project_np
from common.policy.tree import team_forward_np, team_log_std
from common.safety_rows import SafetyRows

MODES = ("train", "deploy")
_PARTIAL_BLOCK = "rollout: fixed_mask must fix whole carrier blocks (all of a carrier's columns or none)"
_NONFINITE_HUMAN = "rollout: human_action is NaN/Inf in a fixed block"


def human_blocks(a_tree: np.ndarray, fixed: np.ndarray, human: np.ndarray, n_agents: int):
    """``(a_st, human_carrier)``: the human's measured action replaces the trees' in
    fixed blocks ([B,d], fixed and human broadcast to it), and which carrier blocks
    are the human's [B,N]. Raises on a partly fixed block or a NaN/Inf human entry.
    The compiled kernel; ``reference.human_blocks`` is its numpy twin."""
    a_st, human_carrier, error = proposal_kernels.human_blocks(a_tree, fixed, human, a_tree.shape[1] // n_agents)
    if error == proposal_kernels.PARTIAL_BLOCK:
        raise ValueError(_PARTIAL_BLOCK)
    if error == proposal_kernels.NONFINITE_HUMAN:
        raise ValueError(_NONFINITE_HUMAN)
    return a_st, human_carrier


def propose(
    params: Mapping[str, np.ndarray],
    obs: np.ndarray,
    rows: SafetyRows,
    human_action: np.ndarray,
    rng: np.random.Generator | None,
    mode: str = "train",
    *,
    kappa: float = 0.0,
    use_sail: bool = True,
    sail_config: SailConfig = SailConfig(),
    proposal_config: ProposalConfig = ProposalConfig(),
) -> dict[str, np.ndarray]:
    """One actor step for B envs.

    obs [B,N,obs_dim]; ``rows`` the step's SafetyRows (fixed_mask [B,d] or [d]);
    human_action [B,d] (read only where fixed); kappa >= 0 (scalar or [B]): the
    SAIL penalty the learner broadcasts.
    Returns a_st, a_bar, a_prop [B,d] float64; logp [B,N] float64; leaf [B,N]; nodes, sides [B,N,D];
    a_tree [B,d], the trees' own output before the human block replaces theirs (decision traces).
    """
    if mode not in MODES:
        raise ValueError(f"rollout: mode must be one of {MODES}, got {mode!r}")
    a_tree, leaf, nodes, sides = team_forward_np(params, obs)
    B, d = a_tree.shape
    n_agents = leaf.shape[1]
    fixed = np.broadcast_to(np.asarray(rows.fixed_mask, dtype=bool), (B, d))
    human = np.broadcast_to(np.asarray(human_action, dtype=np.float64), (B, d))
    a_st, human_carrier = human_blocks(a_tree, fixed, human, n_agents)

    if mode == "deploy":
        return dict(a_st=a_st, a_bar=a_st.copy(), a_prop=a_st.copy(), logp=np.zeros((B, n_agents)),
                    leaf=leaf, nodes=nodes, sides=sides, a_tree=a_tree)

    if use_sail:
        a_bar = sail_project_np(a_st, rows.C, rows.c, np.asarray(rows.row_mask, dtype=bool), kappa,
                                fixed_mask=fixed, fixed_action=human, config=sail_config)
    else:
        a_bar = a_st.copy()
    a_prop, logp = proposal_sample_np(a_bar, team_log_std(params), rng, proposal_config,
                                      human_carrier=human_carrier, human_action=human)
    return dict(a_st=a_st, a_bar=a_bar, a_prop=a_prop, logp=logp, leaf=leaf, nodes=nodes, sides=sides,
                a_tree=a_tree)
