"""The classic exploration tasks (`coherent_jax.envs.brax_env`) against Gymnasium 1.4.0 itself:
``mountain_car_continuous`` = ``MountainCarContinuous-v0``, ``pendulum`` = ``Pendulum-v1``.

Dynamics, reward and termination are compared step for step from the same states: before
each step Gymnasium's env is put in our state (float32, widened to float64) and both step
with the same action. Our state is float32; Gymnasium's car is float32 after its first step
and its pendulum float64 throughout, so observations agree to float32 rounding of one step
(`OBS_TOL`) and rewards to a few float32 ulps of their size (`REWARD_TOL`); terminations
exactly. Time limits and truncation are read from `VecEnv`, the reset distribution by a
two-sample Kolmogorov-Smirnov test against 1,000 of Gymnasium's resets.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats
from test_evaluate import make_run

from coherent_jax.agents.rollout import evaluation_metrics
from coherent_jax.envs import VecEnv, check_task, make_brax_env
from coherent_jax.evaluate import main
from coherent_jax.run.evaluation import gymnasium_action_map

gym = pytest.importorskip("gymnasium")

IDS = {"mountain_car_continuous": "MountainCarContinuous-v0", "pendulum": "Pendulum-v1"}
BOUND = {"mountain_car_continuous": 1.0, "pendulum": 2.0}  # Gymnasium's action bounds
OBS_TOL = 1e-6  # absolute: |obs| <= 8 (pendulum's speed), float32 rounding of one step
# Absolute, about 2 float32 ulps of the largest reward: the car's goal step pays 100 - 0.1 a^2
# (ulp 7.6e-6 at 100), the pendulum's cost reaches 16.3 (ulp 1.9e-6).
REWARD_TOL = {"mountain_car_continuous": 1.5e-5, "pendulum": 4e-6}


def bang_bang(obs):
    """Full force in the direction of motion: swings the car to the goal in about 100 steps."""
    return jnp.where(obs[..., 1:2] >= 0, 1.0, -1.0)


def _compare(task, actions_of, steps, seed):
    """Steps ours and Gymnasium's env from the same state each step (Gymnasium's reset first);
    returns the largest observation and reward differences and the terminations [steps] of both."""
    env, theirs = make_brax_env(task), gym.make(IDS[task]).unwrapped
    step = jax.jit(env.step)
    obs0, _ = theirs.reset(seed=seed)
    state = env.reset(jax.random.PRNGKey(0))
    state = state.replace(pipeline_state=jnp.asarray(theirs.state, jnp.float32), obs=jnp.asarray(obs0))
    d_obs, d_rew, ours_done, their_done = 0.0, 0.0, [], []
    for t in range(steps):
        a = np.asarray(actions_of(t, np.asarray(state.obs)), np.float32).reshape(1)
        theirs.state = np.asarray(state.pipeline_state, np.float64)
        obs, reward, terminated, truncated, _ = theirs.step(a * BOUND[task])
        state = step(state, jnp.asarray(a))
        d_obs = max(d_obs, float(np.abs(np.asarray(state.obs) - obs).max()))
        d_rew = max(d_rew, abs(float(state.reward) - reward))
        ours_done.append(bool(state.done > 0.5))
        their_done.append(terminated)
        assert not truncated  # the unwrapped env has no time limit
        if terminated:
            break
    return d_obs, d_rew, ours_done, their_done


@pytest.mark.parametrize("task", sorted(IDS))
def test_classic_steps_equal_gymnasium_from_the_same_states(task):
    """Random actions (and beyond the bounds: Gymnasium clips them, the reward of the car
    takes them as given) from Gymnasium's reset, for a whole episode's length."""
    rng = np.random.default_rng(1)
    steps = check_task(task).episode_length
    d_obs, d_rew, ours, theirs = _compare(task, lambda t, o: rng.uniform(-1.3, 1.3), steps, seed=2)
    assert d_obs <= OBS_TOL and d_rew <= REWARD_TOL[task], (d_obs, d_rew)
    assert ours == theirs and len(ours) == steps and not any(ours)


def test_classic_mountain_car_terminates_at_the_goal_with_gymnasiums_reward():
    """Bang-bang control reaches the flag: the same step terminates in both, paying 100 - 0.1 a^2;
    the left wall stops the car (velocity 0) on the way, as in Gymnasium."""
    for seed in range(3):
        d_obs, d_rew, ours, theirs = _compare(
            "mountain_car_continuous", lambda t, o: bang_bang(o), 999, seed=seed
        )
        assert d_obs <= OBS_TOL and d_rew <= REWARD_TOL["mountain_car_continuous"], (d_obs, d_rew)
        assert ours == theirs and ours[-1] and sum(ours) == 1 and len(ours) < 200


def test_classic_mountain_car_left_wall_is_inelastic():
    env = make_brax_env("mountain_car_continuous")
    state = env.reset(jax.random.PRNGKey(0)).replace(pipeline_state=jnp.array([-1.19, -0.05]))
    theirs = gym.make(IDS["mountain_car_continuous"]).unwrapped
    theirs.reset(seed=0)
    theirs.state = np.array([-1.19, -0.05])
    obs, *_ = theirs.step(np.array([-1.0], np.float32))
    ours = env.step(state, jnp.array([-1.0])).obs
    assert ours[0] == np.float32(-1.2) and float(ours[1]) == 0.0 and np.allclose(ours, obs, atol=OBS_TOL)


@pytest.mark.parametrize("task", sorted(IDS))
def test_classic_reset_distribution_is_gymnasiums(task):
    """Car: position U(-0.6, -0.4), velocity 0; pendulum: angle U(-pi, pi), speed U(-1, 1).
    KS test per varying observation dimension (level 1e-3), and the support's bounds."""
    env = make_brax_env(task)
    ours = np.asarray(jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(3), 1000)).pipeline_state)
    g = gym.make(IDS[task]).unwrapped
    theirs = []
    for i in range(1000):
        g.reset(seed=i)
        theirs.append(np.array(g.state, np.float64))
    theirs = np.stack(theirs)
    high = np.array([-0.4, 0.0]) if task == "mountain_car_continuous" else np.array([np.pi, 1.0])
    low = np.array([-0.6, 0.0]) if task == "mountain_car_continuous" else -high
    assert np.all(ours >= low - 1e-6) and np.all(ours <= high + 1e-6)
    for d in range(2):
        if high[d] == low[d]:
            assert np.all(ours[:, d] == low[d]) and np.all(theirs[:, d] == low[d])
            continue
        assert stats.ks_2samp(ours[:, d], theirs[:, d]).pvalue > 1e-3, d
        assert ours[:, d].max() - ours[:, d].min() > 0.9 * (high[d] - low[d])


@pytest.mark.parametrize("task", sorted(IDS))
def test_classic_time_limits_and_truncation_are_gymnasiums(task):
    """999 and 200 steps by default (Gymnasium's registered limits), truncated (bootstrapped) at
    the limit; the pendulum never terminates."""
    spec = check_task(task)
    assert spec.gymnasium_id == IDS[task]
    assert spec.episode_length == gym.spec(IDS[task]).max_episode_steps
    env = VecEnv(task, 2)
    state = env.reset(jax.random.PRNGKey(0))
    step = jax.jit(env.step)
    for t in range(env.episode_length):
        state, out = step(state, jnp.zeros((2, 1)))
        assert not bool(out.terminated.any())
        assert bool(out.truncated.all()) == (t == env.episode_length - 1)
    # The car standing still pays nothing and never reaches the goal: return exactly 0.
    if task == "mountain_car_continuous":
        assert np.all(np.asarray(out.episode_return) == 0.0)


def test_classic_pendulum_maps_the_action_onto_its_torque_bounds():
    """The agent's action in [-1, 1] is the torque / 2 (`to_bounds`); beyond 1 it is clipped."""
    env = make_brax_env("pendulum")
    state = env.reset(jax.random.PRNGKey(0)).replace(pipeline_state=jnp.array([0.5, 0.0]))
    g = gym.make("Pendulum-v1").unwrapped
    g.reset(seed=0)
    for a in (0.25, 1.0):
        g.state = np.array([0.5, 0.0])
        obs, reward, *_ = g.step(np.array([2 * a], np.float32))
        out = env.step(state, jnp.array([a]))
        assert np.allclose(out.obs, obs, atol=OBS_TOL) and abs(float(out.reward) - reward) < 1e-5
    clipped = VecEnv("pendulum", 1).step
    s = VecEnv("pendulum", 1).reset(jax.random.PRNGKey(0))
    assert np.array_equal(clipped(s, jnp.array([[1.7]]))[1].reward, clipped(s, jnp.array([[1.0]]))[1].reward)
    space = g.action_space
    assert float(gymnasium_action_map("pendulum", space)(jnp.array([0.25]))[0]) == 0.5


def test_classic_goal_reached_is_logged_for_the_car_only():
    """``eval/goal_reached``: the fraction of evaluation episodes that ended at the goal; a
    reached episode's return is positive, one that did not reach it is not."""
    car = VecEnv("mountain_car_continuous", 4)
    reached = evaluation_metrics(car, bang_bang, jax.random.PRNGKey(0))
    assert float(reached["eval/goal_reached"]) == 1.0 and 0 < float(reached["eval/episode_return"]) < 100
    idle = evaluation_metrics(car, lambda o: 0.5 * jnp.ones((4, 1)), jax.random.PRNGKey(0))
    assert float(idle["eval/goal_reached"]) == 0.0 and float(idle["eval/episode_return"]) < 0
    assert check_task("mountain_car_continuous").goal and not check_task("pendulum").goal
    assert "eval/goal_reached" not in evaluation_metrics(
        VecEnv("pendulum", 2), lambda o: o[:, :1], jax.random.PRNGKey(0)
    )


@pytest.mark.parametrize("task", sorted(IDS))
def test_classic_evaluate_runs_the_policy_in_gymnasium(tmp_path, capsys, task):
    """``engine=gymnasium`` on a fresh (untrained) policy: Gymnasium's episodes have the task's
    length and a return within the episodes' spread of ours (different initial draws)."""
    overrides = [f"env={task}", "num_envs=2", "ppo.num_minibatches=1", "progress=false"]
    run = make_run(tmp_path / "run", overrides)
    assert main([str(run), "episodes=8", "engine=gymnasium", "seed=1"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["gymnasium_id"] == IDS[task]
    assert result["gymnasium_episode_length_mean"] == result["episode_length_mean"]
    spread = np.sqrt((result["return_std"] ** 2 + result["gymnasium_return_std"] ** 2) / 2)
    assert abs(result["gymnasium_return_mean"] - result["return_mean"]) <= max(3 * spread, 1.0), result


def test_classic_registry_names_their_gymnasium_ids_and_builds_them_as_jax_envs():
    """Gymnasium ids for evaluate's engine=gymnasium; pure JAX (no MuJoCo physics to choose)."""
    from coherent_jax.envs.registry import CLASSIC_IDS, brax_counterpart, resolve_physics

    assert CLASSIC_IDS == {v: k for k, v in IDS.items()}
    for task in IDS:
        assert brax_counterpart(task) == task and resolve_physics(task, "auto") == "jax"
        assert make_brax_env(task).backend == "jax"
    assert brax_counterpart("hopper") == "brax-hopper"


def test_classic_evaluate_without_gymnasium_names_it_in_one_line(tmp_path, capsys, monkeypatch):
    """A classic task needs Gymnasium alone (not gymnasium[mujoco]); refused before evaluating."""
    import sys

    from test_evaluate import make_fake_run

    run = make_fake_run(tmp_path / "run", ["env=pendulum", "num_envs=2", "ppo.num_minibatches=1"])
    monkeypatch.setitem(sys.modules, "gymnasium.envs.classic_control", None)
    assert main([str(run), "engine=gymnasium"]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "needs gymnasium (" in err[0] and '".[gym]"' in err[0], err
    assert "evaluating" not in captured.out
