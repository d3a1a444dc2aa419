"""`coherent_jax.policy`: predict (Stable-Baselines3's convention) on one tiny trained run per
algorithm, shared by the module; stochastic acting with the strategy's noise state."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import yaml
from test_export import ACT, CASES, OBS, random_policy

import coherent_jax
import coherent_jax.policy as policy_package
from coherent_jax import api
from coherent_jax.config import make_config
from coherent_jax.envs.action_map import ActionMap
from coherent_jax.export import main as export_main
from coherent_jax.policy import Policy, PolicyState, load_policy

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


def test_one_policy_class_and_one_load_policy_under_every_public_name():
    """`Policy` and `load_policy` are the package's one policy and one loader (`TrainedPolicy`
    and `PolicyFunction`, its former names, are tests/test_compat.py's)."""
    assert coherent_jax.Policy is Policy
    assert coherent_jax.load_policy is api.load_policy is policy_package.load_policy
    assert not hasattr(policy_package, "read_policy") and "PolicyError" in policy_package.__all__


@pytest.mark.slow
def test_predict_deterministic_one_and_batch(ppo_run):
    policy = load_policy(ppo_run)
    assert isinstance(policy, Policy) and coherent_jax.load_policy(ppo_run).origin == policy.origin
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
    with pytest.raises(
        ValueError, match=r"invalid episode_start of shape \[2\] \(allowed: one bool, or \[3\]\)$"
    ):
        a.predict(obs, s1, episode_start=[True, False], deterministic=False)


@pytest.mark.parametrize("start", [True, False, np.True_, np.array(False)])
def test_one_episode_start_bool_is_every_envs(start):
    """``episode_start=True`` (one bool, as docs/api.md allows) with a batch of 100: every env
    starts, as ``[True] * 100`` does; False: none does."""
    policy = random_policy("ppo", "coherent", {})
    obs = np.random.default_rng(5).normal(size=(100, OBS)).astype(np.float32)
    state = policy.predict(obs, policy.initial_state(100, seed=1), deterministic=False)[1]
    one, _ = policy.predict(obs, state, episode_start=start, deterministic=False)
    each, _ = policy.predict(obs, state, episode_start=np.full(100, bool(start)), deterministic=False)
    np.testing.assert_array_equal(one, each)


# ------------------------------------------------------------ every strategy, stochastic
@pytest.mark.parametrize(("algo", "explore", "extra"), CASES, ids=lambda v: str(v))
def test_stochastic_predict_for_every_strategy(algo, explore, extra):
    policy = random_policy(algo, explore, extra)
    obs = np.random.default_rng(2).normal(size=(4, OBS)).astype(np.float32)
    state = policy.initial_state(4, seed=1)
    actions = []
    for t in range(3):
        a, state = policy.predict(obs, state, episode_start=np.full(4, t == 0), deterministic=False)
        actions.append(a)
    again, _ = policy.predict(obs, policy.initial_state(4, seed=1), np.ones(4, bool), deterministic=False)
    np.testing.assert_array_equal(again, actions[0])  # seeded
    a = np.stack(actions)
    assert a.shape == (3, 4, ACT) and np.all(np.isfinite(a))
    assert np.all(a >= policy.action_map.low) and np.all(a <= policy.action_map.high)
    assert not np.allclose(a[0], policy.predict(obs)[0])  # it explores


@pytest.mark.parametrize("beta", [0.0, 1.0])
def test_coherent_weight_noise_autocorrelation_is_the_chains(beta):
    """z_t = (1 - beta) z_{t-1} + sqrt(2 beta - beta^2) eps (eqs. 4.1-4.4): lag-1 autocorrelation
    1 - beta within an episode, and a fresh draw where episode_start says."""
    policy = random_policy("ppo", "coherent", {"coherent.beta": beta})
    n, steps = 32, 60
    obs = np.random.default_rng(3).normal(size=(n, OBS)).astype(np.float32)
    state = policy.initial_state(n, seed=4)
    zs = []
    for t in range(steps):
        _, state = policy.predict(obs, state, episode_start=np.full(n, t == 0), deterministic=False)
        zs.append(np.asarray(state.carry.z))
    z = np.stack(zs).astype(np.float64)  # [T, n, p, q+1]
    rho = np.sum(z[1:] * z[:-1]) / np.sqrt(np.sum(z[1:] ** 2) * np.sum(z[:-1] ** 2))
    samples = z[1:].size
    assert abs(rho - (1 - beta)) < 4 / np.sqrt(samples), (rho, beta)
    assert np.var(z) == pytest.approx(1.0, abs=0.15)  # the chain's stationary variance
    _, restarted = policy.predict(obs, state, episode_start=np.ones(n, bool), deterministic=False)
    fresh = np.asarray(restarted.carry.z, np.float64)
    assert abs(np.mean(fresh * z[-1])) < 0.1  # a new draw, uncorrelated with the last


# ------------------------------------------------------------ Gymnasium, by hand
def test_predict_in_a_gymnasium_loop_equals_evaluate_engine_gymnasium():
    """A hand-written gymnasium.make("InvertedPendulum-v5") loop with predict returns what
    evaluate engine=gymnasium returns (`gymnasium_returns`), episode for episode; the task's
    actions are in [-3, 3]."""
    from coherent_jax.envs.vec_env import VecEnv
    from coherent_jax.run.evaluation import gymnasium_returns

    env = VecEnv("inverted_pendulum", 1, None, "native", 1)
    amap = ActionMap.of_physics(env.env, env.action_size)
    policy = random_policy("ppo", "coherent", {}, seed=5, env="inverted_pendulum", sizes=(4, 1), amap=amap)
    assert float(policy.action_space.high[0]) == 3.0
    episodes, length, seed = 3, 60, 11
    want, want_len = gymnasium_returns(policy.policy, "inverted_pendulum", length, episodes, seed)
    seeds = np.random.SeedSequence(seed).generate_state(episodes)
    got, seen = [], []
    for s in seeds:
        gym_env = gymnasium.make("InvertedPendulum-v5", max_episode_steps=length)
        obs, _ = gym_env.reset(seed=int(s))
        total, done = 0.0, False
        while not done:
            action, _ = policy.predict(obs)
            seen.append(action)
            obs, reward, terminated, truncated, _ = gym_env.step(action)
            total += reward
            done = terminated or truncated
        got.append(total)
        gym_env.close()
    np.testing.assert_allclose(got, want, rtol=1e-6)
    assert np.max(np.abs(seen)) > 1.0  # the map onto [-3, 3] is in play


# ------------------------------------------------------------ Hub folder
def test_hub_folder_round_trips_through_load_policy(ppo_run, tmp_path):
    """``python -m coherent_jax.export RUN_DIR format=hub`` (its main, in-process) writes the
    folder; load_policy reads it back and predicts as the run directory does."""
    out = tmp_path / "hub"
    args = [str(ppo_run), "format=hub", f"out={out}", "episodes=3"]
    assert export_main(args) == 0
    names = {p.name for p in out.iterdir()}
    assert names >= {"README.md", "config.yaml", "policy.msgpack", "policy.json", "policy.onnx"}
    card = (out / "README.md").read_text()
    front = yaml.safe_load(card.split("---\n")[1])
    meta = front["coherent_jax"]
    assert (meta["task"], meta["algorithm"], meta["strategy"]) == ("pointmass", "ppo", "coherent")
    assert meta["evaluation"]["episodes"] == 3 and "beta" in meta["strategy_settings"]
    assert meta["training_command"].startswith("python -m coherent_jax.train env=pointmass algo=ppo")
    assert meta["library_version"] == coherent_jax.__version__
    shipped, original = load_policy(out), load_policy(ppo_run)
    assert repr(shipped) == repr(original)
    obs = np.random.default_rng(4).normal(size=(50, 6)).astype(np.float32)
    np.testing.assert_array_equal(shipped.predict(obs)[0], original.predict(obs)[0])
    a, _ = shipped.predict(obs, shipped.initial_state(50, seed=2), deterministic=False)
    b, _ = original.predict(obs, original.initial_state(50, seed=2), deterministic=False)
    np.testing.assert_array_equal(a, b)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    assert export_main(args) == 2  # exists: refused, nothing written
    assert export_main([str(ppo_run), "format=onnx", f"out={out / 'README.md'}"]) == 2
    assert sorted(p.name for p in tmp_path.rglob("*")) == before
