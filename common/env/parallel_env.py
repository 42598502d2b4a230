"""PettingZoo ParallelEnv of a single transport environment (BatchEnv with K=1).

    from common.env.parallel_env import parallel_env
    env = parallel_env(scenario="maze", max_steps=400)      # EnvConfig fields as keywords
    obs, infos = env.reset(seed=0)

It works with the ecosystem's standard wrappers (tested): SuperSuit's
``pettingzoo_env_to_vec_env_v1`` (needs ``render_mode``) and TorchRL's
``PettingZooWrapper`` (needs the same ``info`` keys from ``reset`` and ``step``).
"""
from __future__ import annotations

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from common.env.batch_env import BatchEnv
from common.env.config import EnvConfig
from common.spec import JOINT_ACT_DIM, N_CARRIERS


class TransportParallelEnv(ParallelEnv):
    """Agents ``carrier_0..2``; shared reward; safety rows, costs and flags in ``info``
    (the same keys after ``reset`` and every ``step``: the flags are False and the
    cost 0 at a reset).

    Once an episode ends the env is done (PettingZoo semantics): agents is emptied and
    ``reset`` must be called. The underlying BatchEnv's auto-reset is not exposed.
    The MuJoCo model is compiled once, on the first ``reset``, and every later
    episode reuses it: ``reset(seed=s)`` reseeds it (the same episodes as a fresh env
    with seed ``s``), ``reset()`` draws the next episode of the current stream.
    The finished episode's metrics are ``episode`` (None until one ends).
    """

    metadata = {"name": "sage_transport_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(self, cfg: EnvConfig | None = None, seed: int = 0, render_mode: str | None = None):
        if render_mode is not None:
            raise ValueError(f"render_mode {render_mode!r} is not supported (render_modes: none; "
                             "`sage env render` draws a scenario, `sage eval --video` an episode)")
        self.cfg = cfg or EnvConfig()
        self.render_mode = render_mode
        self._seed = seed
        self.possible_agents = [f"carrier_{i}" for i in range(N_CARRIERS)]
        self.agents = []
        self._env: BatchEnv | None = None
        self.episode: dict | None = None
        self._obs_space = {a: spaces.Box(-np.inf, np.inf, (BatchEnv.obs_dim,), np.float32) for a in self.possible_agents}
        self._act_space = {a: spaces.Box(-1.0, 1.0, (BatchEnv.act_dim,), np.float32) for a in self.possible_agents}
        self.state_space = spaces.Box(-np.inf, np.inf, (BatchEnv.state_dim,), np.float32)

    def observation_space(self, agent):
        return self._obs_space[agent]

    def action_space(self, agent):
        return self._act_space[agent]

    def _infos(self, out, agents):
        info = {
            "C": out["C"][0], "c": out["c"][0], "row_mask": out["row_mask"][0], "fixed_mask": out["fixed_mask"][0],
            "human_action": out["human_action"][0], "progress": float(out["progress"][0]),
        }
        for key in ("collision", "drop", "success"):
            info[key] = bool(out[key][0]) if key in out else False
        info["cost"] = float(info["collision"])
        return {a: dict(info) for a in agents}

    def reset(self, seed=None, options=None):
        if self._env is None:   # compile the scenario's MJCF once; later episodes reuse it
            self._seed = self._seed if seed is None else seed
            self._env = BatchEnv(self.cfg, num_envs=1, seed=self._seed)
        elif seed is not None:
            self._seed = seed
            self._env.reseed(seed)
        out = self._env.reset()
        self.agents = list(self.possible_agents)
        self.episode = None
        self._last = out
        return {a: out["obs"][0, i] for i, a in enumerate(self.agents)}, self._infos(out, self.agents)

    def state(self):
        return self._last["state"][0]

    def step(self, actions):
        if not self.agents:
            raise RuntimeError("episode is over; call reset()")
        a = np.zeros((1, JOINT_ACT_DIM))
        for i, agent in enumerate(self.possible_agents):
            if agent in actions:
                a[0, 3 * i:3 * i + 3] = actions[agent]
        out = self._env.step(a)
        term, trunc = bool(out["terminated"][0]), bool(out["truncated"][0])
        ended = term or trunc
        obs_arr = out["final_obs"][0] if ended else out["obs"][0]
        agents = list(self.agents)
        obs = {ag: obs_arr[i] for i, ag in enumerate(agents)}
        rew = {ag: float(out["reward"][0]) for ag in agents}
        terms = {ag: term for ag in agents}
        truncs = {ag: trunc for ag in agents}
        infos = self._infos(out, agents)
        self._last = dict(out, state=out["final_state"] if ended else out["state"])
        if ended:
            self.episode = out["episodes"][0]
            self.agents = []
        return obs, rew, terms, truncs, infos


def parallel_env(scenario: str = "narrow_gate", seed: int = 0, render_mode: str | None = None,
                 **env_kwargs) -> TransportParallelEnv:
    """PettingZoo's constructor convention: ``parallel_env(scenario="maze", max_steps=400)``;
    the keywords are ``EnvConfig`` fields (an unknown one is a ``TypeError``)."""
    return TransportParallelEnv(EnvConfig(scenario=scenario, **env_kwargs), seed=seed, render_mode=render_mode)
