"""Learning smoke test: on a contextual bandit (reward = -||a - target(o)||^2)
a few dozen updates of sage and happo must raise the reward. This can fail."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from common.algos import AlgoConfig, make_method
from common.algos.synthetic import BanditTask, collect

OBS, UPDATES = 6, 20


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.mark.parametrize("name", ["sage", "happo"])
def test_updates_raise_bandit_reward(name):
    cfg = AlgoConfig(actor_lr=3e-3, critic_lr=3e-3, epochs=3, minibatches=2,
                     critic_hidden=32, encoder_latent=8, ent_coef=0.0)
    m = make_method(name, cfg, OBS, 0)
    task = BanditTask(obs_dim=OBS, seed=1, n_rows=8, row_frac=0.3)
    rng = np.random.default_rng(0)
    held_out = task.sample_context(np.random.default_rng(123), 1, 256)["obs"][0]

    def deterministic_reward() -> float:
        with torch.no_grad():
            a = m.policy(torch.as_tensor(held_out), 1.0).action.double().numpy()
        return float(task.reward(held_out, a).mean())

    before = deterministic_reward()
    sampled = []
    for u in range(UPDATES):
        batch = collect(m, task, 8, 16, u / UPDATES, rng)
        sampled.append(float(batch["reward"].mean()))
        m.update(batch, u / UPDATES)
    after = deterministic_reward()
    # initial policy: about -1.8 (deterministic) and -3.5 (sampled); optimum 0
    assert after > before + 0.5, (before, after)
    assert np.mean(sampled[-3:]) > np.mean(sampled[:3]) + 0.5, sampled
