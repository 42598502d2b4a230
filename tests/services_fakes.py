"""Small stand-ins for the env, the propose step, the QP and a method, used
only to test the service loops (the real ones live in other areas)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

N, D, M, O, S = 3, 9, 4, 5, 6


class FakeBatchEnv:
    """BatchEnv-shaped: K envs, episodes of ``ep_len`` steps, one fixed row
    a_0 >= 0.5 (so unfiltered proposals are recognisable). Records every
    action it executes."""

    def __init__(self, num_envs=2, ep_len=5, seed=0):
        self.K, self.ep_len = num_envs, ep_len
        self.obs_dim, self.state_dim, self.n_agents, self.act_dim, self.max_rows = O, S, N, 3, M
        self.rng = np.random.default_rng(seed)
        self.t = np.zeros(num_envs, int)
        self.executed: list[np.ndarray] = []

    def _obs(self):
        K = self.K
        C = np.zeros((K, M, D))
        C[:, 0, 0] = 1.0
        c = np.zeros((K, M))
        c[:, 0] = 0.5
        row_mask = np.zeros((K, M), bool)
        row_mask[:, 0] = True
        return {"obs": self.rng.normal(size=(K, N, O)).astype(np.float32),
                "state": self.rng.normal(size=(K, S)).astype(np.float32),
                "C": C, "c": c, "row_mask": row_mask, "fixed_mask": np.zeros((K, D), bool),
                "human_action": np.zeros((K, D)), "progress": self.t / self.ep_len}

    def reset(self):
        self.t[:] = 0
        return self._obs()

    def step(self, actions):
        actions = np.asarray(actions, dtype=np.float64)
        assert actions.shape == (self.K, D)
        self.executed.append(actions.copy())
        self.t += 1
        done = self.t >= self.ep_len
        final_state = np.zeros((self.K, S), np.float32)
        episodes = [{"success": float(i % 2 == 0), "return": 1.0, "length": float(self.ep_len)}
                    for i in np.flatnonzero(done)]
        self.t[done] = 0
        out = self._obs()
        out.update(reward=-np.abs(actions).sum(1), terminated=np.zeros(self.K, bool), truncated=done,
                   collision=np.zeros(self.K, bool), final_obs=np.zeros((self.K, N, O), np.float32),
                   final_state=final_state, episodes=episodes)
        return out


def fake_propose(params, obs, rows, human_action, rng, mode="train", *, kappa=0.0, use_sail=True):
    K = obs.shape[0]
    a_st = np.tanh(obs.reshape(K, -1)[:, :D] * params["carrier_0/W"].ravel()[0])
    a_bar = a_st.copy()
    a_prop = np.clip(a_bar + 0.3 * rng.normal(size=a_bar.shape), -1, 1) if mode == "train" else a_st
    return {"a_st": a_st, "a_bar": a_bar, "a_prop": a_prop, "logp": np.zeros((K, N)),
            "leaf": np.zeros((K, N), np.int64), "nodes": np.zeros((K, N, 1), np.int64),
            "sides": np.zeros((K, N, 1), bool)}


def fake_solve(a_prop, rows):
    """Exact for the fake env's rows (one lower bound per coordinate) + box."""
    C, c, row_mask = rows.C, rows.c, rows.row_mask
    a = np.clip(a_prop, -1, 1)
    for j in range(C.shape[1]):
        for k in range(D):
            on = row_mask[:, j] & (C[:, j, k] == 1.0) & (np.abs(C[:, j]).sum(1) == 1.0)
            a[on, k] = np.maximum(a[on, k], c[on, j])
    n = np.linalg.norm(a - a_prop, axis=1)
    B = a.shape[0]
    return SimpleNamespace(a_exec=a, status=np.zeros(B, int), correction_norm=n, slack=np.zeros(B))


class FakeMethod:
    shielded, uses_sail = True, True

    def __init__(self):
        self.w = np.ones((1, O))
        self.n = 0
        self.batches = []

    def policy_params(self):
        """Tree-shaped (depth 1, so actors accept them); fake_propose reads carrier_0/W."""
        out = {"format_version": np.asarray(1.0, np.float32)}
        for i in range(N):
            out.update({f"carrier_{i}/W": self.w.astype(np.float32), f"carrier_{i}/b": np.zeros(1, np.float32),
                        f"carrier_{i}/K": np.zeros((2, 3, O), np.float32),
                        f"carrier_{i}/beta": np.zeros((2, 3), np.float32),
                        f"carrier_{i}/log_std": np.zeros(3, np.float32),
                        f"carrier_{i}/c_a": np.zeros(3, np.float32), f"carrier_{i}/s_a": np.ones(3, np.float32)})
        return out

    def actor_settings(self, progress):
        return {"kappa": 1.0 + progress, "tau": 1.0}

    def update(self, batch, progress):
        self.batches.append(batch)
        self.n += 1
        self.w = self.w * 0.9
        return {"policy_loss": float(batch["reward"].mean()), "n": float(self.n)}

    def state_dict(self):
        return {"w": torch.from_numpy(self.w.copy()), "n": self.n}

    def load_state_dict(self, d):
        self.w = d["w"].numpy().copy()
        self.n = int(d["n"])


def serve_shield(cfg, bus, solve, timeout: float = 60.0):
    """A ShieldService with ``solve`` on a thread, once it is running: (service, stop event, thread)."""
    import threading
    import time

    from services.shield.service import ShieldService

    stop = threading.Event()
    shield = ShieldService(cfg, bus, stop=stop, solve=solve)
    th = threading.Thread(target=shield.run, daemon=True)
    th.start()
    deadline = time.monotonic() + timeout
    while shield.state != "running":
        if time.monotonic() > deadline:
            raise AssertionError(f"the shield did not start within {timeout} s")
        time.sleep(0.01)
    return shield, stop, th
