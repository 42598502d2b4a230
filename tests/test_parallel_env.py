"""The PettingZoo ParallelEnv (common/env/parallel_env.py) with the ecosystem's wrappers:
SuperSuit's ``pettingzoo_env_to_vec_env_v1`` and TorchRL's ``PettingZooWrapper``
(both in the test extra), PettingZoo's own API test, the ``parallel_env`` factory,
and one compiled model reused across episodes."""
from __future__ import annotations

import numpy as np
import pytest

from common.env.config import EnvConfig
from common.env.parallel_env import TransportParallelEnv, parallel_env

ZERO = {f"carrier_{i}": np.zeros(3, np.float32) for i in range(3)}


def _run_episode(env, seed=None):
    """Reset, then zero actions until the episode ends; the observations seen."""
    obs, _ = env.reset(seed=seed)
    seen = [np.stack([obs[a] for a in env.possible_agents])]
    while env.agents:
        obs, *_ = env.step(ZERO)
        seen.append(np.stack([obs[a] for a in env.possible_agents]))
    return np.stack(seen)


def test_factory_builds_the_configured_env_and_refuses_unknown_fields():
    env = parallel_env(scenario="maze", seed=4, max_steps=5, human_slot=2)
    assert env.cfg == EnvConfig("maze", max_steps=5, human_slot=2) and env._seed == 4
    assert env.render_mode is None and env.metadata["render_modes"] == []
    with pytest.raises(TypeError):
        parallel_env(scenario="maze", no_such_field=1)
    with pytest.raises(ValueError, match="scenario must be one of"):
        parallel_env(scenario="nowhere")
    with pytest.raises(ValueError, match="render_mode"):
        parallel_env(render_mode="human")


def test_pettingzoo_parallel_api_through_the_factory():
    from pettingzoo.test import parallel_api_test

    parallel_api_test(parallel_env(scenario="narrow_gate", max_steps=20, seed=1), num_cycles=50)


def test_info_has_the_same_keys_after_reset_and_every_step():
    env = parallel_env(scenario="narrow_gate", max_steps=6)
    _, infos = env.reset(seed=0)
    keys = {a: set(i) for a, i in infos.items()}
    assert set(keys) == set(env.possible_agents)
    assert keys["carrier_0"] >= {"C", "c", "row_mask", "fixed_mask", "human_action", "progress",
                                 "collision", "drop", "success", "cost"}
    assert infos["carrier_0"]["collision"] is False and infos["carrier_0"]["cost"] == 0.0
    steps = 0
    while env.agents:
        _, _, _, _, infos = env.step(ZERO)
        steps += 1
        assert {a: set(i) for a, i in infos.items()} == keys
    assert steps == 6 and env.episode is not None and env.episode["steps"] == 6


def test_the_model_is_compiled_once_and_reseeding_repeats_episodes(monkeypatch):
    from common.env import physics

    compiled = []
    original = physics.compile_model
    monkeypatch.setattr(physics, "compile_model", lambda xml: compiled.append(1) or original(xml))
    env = TransportParallelEnv(EnvConfig("narrow_gate", max_steps=8), seed=0)
    first = _run_episode(env, seed=3)
    batch = env._env
    second = _run_episode(env)            # the stream goes on: another episode
    again = _run_episode(env, seed=3)     # reseeded: the first episode again
    assert env._env is batch and len(compiled) == 1
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first[0], second[0])
    # and the same episode a fresh env with that seed gives (a second compile, its own)
    fresh = _run_episode(TransportParallelEnv(EnvConfig("narrow_gate", max_steps=8), seed=3))
    np.testing.assert_array_equal(first, fresh)
    assert len(compiled) == 2


def test_supersuit_vector_env():
    ss = pytest.importorskip("supersuit")
    vec = ss.pettingzoo_env_to_vec_env_v1(parallel_env(scenario="narrow_gate", max_steps=5))
    obs, _ = vec.reset(seed=0)
    assert obs.shape == (3, 34) and vec.num_envs == 3
    for t in range(7):   # past the end of an episode: the vector env resets it
        obs, rew, term, trunc, _ = vec.step(np.zeros((3, 3), np.float32))
        assert obs.shape == (3, 34) and np.isfinite(obs).all() and rew.shape == (3,)
        assert bool(trunc.all()) == (t == 4)


@pytest.mark.sweep
def test_torchrl_wrapper_specs_and_rollout():
    pytest.importorskip("torchrl")
    from torchrl.envs.libs.pettingzoo import PettingZooWrapper
    from torchrl.envs.utils import check_env_specs

    env = PettingZooWrapper(env=parallel_env(scenario="narrow_gate", max_steps=5), return_state=True)
    check_env_specs(env)
    td = env.rollout(8, break_when_any_done=False)
    assert td["next", "carrier", "observation"].shape == (8, 3, 34)
    assert td["next", "carrier", "info", "C"].shape[:2] == (8, 3)
    assert bool(td["next", "truncated"][4]) and not bool(td["next", "truncated"][3])


def test_readme_example_runs():
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = text.split("from common.env.parallel_env import parallel_env", 1)[1].split("```", 1)[0]
    scope: dict = {}
    exec("from common.env.parallel_env import parallel_env" + block, scope)   # the README's own lines
    assert scope["env"].cfg.scenario == "maze" and set(scope["rewards"]) == set(scope["env"].possible_agents)
