"""Small fixed trees for tests and demos, in the flat ``export_params`` layout."""
from __future__ import annotations

import numpy as np


def random_team_params(n_agents: int = 3, obs_dim: int = 6, depth: int = 3, act_dim: int = 3,
                       seed: int = 0, gain: float = 0.5) -> dict[str, np.ndarray]:
    """Random oblique trees: unit-scale split vectors, thresholds near 0, bounds [-1, 1]."""
    rng = np.random.default_rng(seed)
    n_int, n_leaves = 2 ** depth - 1, 2 ** depth
    params: dict[str, np.ndarray] = {"format_version": np.array(1)}
    for i in range(n_agents):
        params[f"carrier_{i}/W"] = rng.normal(size=(n_int, obs_dim))
        params[f"carrier_{i}/b"] = rng.normal(scale=0.3, size=n_int)
        params[f"carrier_{i}/K"] = rng.normal(scale=gain, size=(n_leaves, act_dim, obs_dim))
        params[f"carrier_{i}/beta"] = rng.normal(scale=0.5, size=(n_leaves, act_dim))
        params[f"carrier_{i}/log_std"] = np.full(act_dim, -0.5)
        params[f"carrier_{i}/c_a"] = np.zeros(act_dim)
        params[f"carrier_{i}/s_a"] = np.ones(act_dim)
    return params
