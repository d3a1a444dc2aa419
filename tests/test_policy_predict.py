"""`coherent_jax.policy`: predict (Stable-Baselines3's convention) on one tiny trained run per
algorithm, shared by the module; stochastic acting with the strategy's noise state."""

from __future__ import annotations

import numpy as np
import pytest

import coherent_jax
from coherent_jax.config import make_config
from coherent_jax.policy import PolicyState, TrainedPolicy, load_policy

TINY = {
    "env": "pointmass",
    "num_envs": 4,
    "unroll_length": 8,
    "episode_length": 20,
    "total_steps": 32,  # one iteration
    "eval_every": 1,
    "eval_episodes": 2,
    "policy_hidden": [8],
    "value_hidden": [8],
    "ppo": {"num_epochs": 1, "num_minibatches": 1},
    "progress": False,
    "tensorboard": False,
}


@pytest.fixture(scope="module")
def ppo_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("policy") / "ppo"
    coherent_jax.learn(make_config({**TINY, "explore": "coherent", "run_dir": str(run_dir)}))
    return run_dir


def test_predict_deterministic_one_and_batch(ppo_run):
    policy = load_policy(ppo_run)
    assert isinstance(policy, TrainedPolicy) and coherent_jax.load_policy(ppo_run).origin == policy.origin
    assert policy.observation_space.shape == (6,) and policy.action_space.shape == (2,)
    text = repr(policy)
    for part in ("task='pointmass'", "algo='ppo'", "explore='coherent'", "env_steps=32"):
        assert part in text, text
    obs = np.random.default_rng(0).normal(size=(5, 6)).astype(np.float32) * 3
    actions, state = policy.predict(obs)
    assert state is None and actions.shape == (5, 2) and actions.dtype == np.float32
    want = np.clip(np.asarray(policy.policy.mean_action(obs)), -1, 1)
    np.testing.assert_allclose(actions, want, rtol=1e-6)
    one, _ = policy.predict(obs[2])
    np.testing.assert_allclose(one, actions[2], rtol=1e-6)
    np.testing.assert_array_equal(policy(obs), actions)  # the old call
    assert policy.action_space.contains(actions[0])


def test_predict_stochastic_is_seeded_and_resets_where_told(ppo_run):
    obs = np.random.default_rng(1).normal(size=(3, 6)).astype(np.float32)
    a = load_policy(ppo_run, seed=3)
    b = load_policy(ppo_run, seed=3)
    act_a, st_a = a.predict(obs, deterministic=False)
    act_b, st_b = b.predict(obs, deterministic=False)
    assert isinstance(st_a, PolicyState)
    np.testing.assert_array_equal(act_a, act_b)
    assert not np.allclose(act_a, a.predict(obs)[0])  # noise
    s1 = a.initial_state(3, seed=7)
    x1, _ = a.predict(obs, s1, episode_start=np.ones(3, bool), deterministic=False)
    x2, _ = a.predict(obs, a.initial_state(3, seed=7), episode_start=np.ones(3, bool), deterministic=False)
    np.testing.assert_array_equal(x1, x2)
    with pytest.raises(ValueError, match=r"invalid episode_start of shape \[2\] \(allowed: \[3\]\)"):
        a.predict(obs, s1, episode_start=[True, False], deterministic=False)
