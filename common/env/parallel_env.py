"""PettingZoo ParallelEnv wrapper of a single transport environment (BatchEnv with K=1)."""
from __future__ import annotations

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from common.env.batch_env import BatchEnv
from common.env.config import EnvConfig
from common.spec import JOINT_ACT_DIM, N_CARRIERS


class TransportParallelEnv(ParallelEnv):
    """Agents ``carrier_0..2``; shared reward; safety rows, costs and flags in ``info``.

    Once an episode ends the env is done (PettingZoo semantics): agents is emptied and
    ``reset`` must be called. The underlying BatchEnv's auto-reset is not exposed.
    """

    metadata = {"name": "sage_transport_v0", "render_modes": []}

    def __init__(self, cfg: EnvConfig | None = None, seed: int = 0):
        self.cfg = cfg or EnvConfig()
        self._seed = seed
        self.possible_agents = [f"carrier_{i}" for i in range(N_CARRIERS)]
        self.agents = []
        self._env = None
        self._obs_space = {a: spaces.Box(-np.inf, np.inf, (BatchEnv.obs_dim,), np.float32) for a in self.possible_agents}
        self._act_space = {a: spaces.Box(-1.0, 1.0, (BatchEnv.act_dim,), np.float32) for a in self.possible_agents}
        self.state_space = spaces.Box(-np.inf, np.inf, (BatchEnv.state_dim,), np.float32)

    def observation_space(self, agent):
        return self._obs_space[agent]

    def action_space(self, agent):
        return self._act_space[agent]

    def _infos(self, out):
        info = {
            "C": out["C"][0], "c": out["c"][0], "row_mask": out["row_mask"][0], "fixed_mask": out["fixed_mask"][0],
            "human_action": out["human_action"][0], "progress": float(out["progress"][0]),
        }
        for key in ("collision", "drop", "success"):
            if key in out:
                info[key] = bool(out[key][0])
        if "collision" in out:
            info["cost"] = float(out["collision"][0])
        if out.get("episodes"):
            info["episode"] = out["episodes"][0]
        return {a: dict(info) for a in self.agents}

    def reset(self, seed=None, options=None):
        if seed is not None:
            self._seed = seed
        self._env = BatchEnv(self.cfg, num_envs=1, seed=self._seed)
        out = self._env.reset()
        self.agents = list(self.possible_agents)
        self._last = out
        return {a: out["obs"][0, i] for i, a in enumerate(self.agents)}, self._infos(out)

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
        infos = self._infos(out)
        self._last = dict(out, state=out["final_state"] if ended else out["state"])
        if ended:
            self.agents = []
        return obs, rew, terms, truncs, infos
