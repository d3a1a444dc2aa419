"""Gymnasium's MuJoCo v5 tasks on native MuJoCo against Gymnasium 1.4.0 itself.

Native physics compiles in about a second per task, so each case runs a few hundred
steps in one jitted scan and Gymnasium's own env beside it.
"""

import os

import jax
import numpy as np
import pytest
from scipy import stats

from coherent_jax.envs import VecEnv, check_task
from coherent_jax.envs.gym_v5 import EPISODE_LENGTH, GYM_TASKS, SHORT_NAMES
from coherent_jax.envs.mujoco_task import control
from coherent_jax.envs.physics import NativePhysics
from coherent_jax.envs.registry import PhysicsError, resolve_physics

gym = pytest.importorskip("gymnasium")

# COHERENT_GYM_STEPS=1000 compares whole 1000-step episodes (the figures of docs/benchmarks.md).
STEPS = int(os.environ.get("COHERENT_GYM_STEPS", "300"))
# Observation slices holding the contact forces (cfrc_ext of every body but the world).
CONTACT_SLICE = {"Ant-v5": slice(27, 105), "Humanoid-v5": slice(270, 348)}


def _gym_env(gym_id: str):
    # The unwrapped env: no time limit, and it keeps stepping after a termination, as ours does.
    return gym.make(gym_id).unwrapped


@pytest.mark.parametrize("gym_id", list(GYM_TASKS))
def test_steps_equal_gymnasium(gym_id):
    """From the same initial states and the same actions, observations, rewards and terminations
    equal Gymnasium's for every one of STEPS steps, to float32 rounding (ours are float32, the
    physics underneath is MuJoCo's float64 on both sides, so trajectories do not drift apart)."""
    env = NativePhysics(gym_id)
    n = 2
    qpos, qvel = jax.vmap(lambda k: env.spec.reset_noise(k, env.init_q, env.nv))(
        jax.random.split(jax.random.PRNGKey(3), n)
    )
    qpos, qvel = np.asarray(qpos), np.asarray(qvel)
    actions = np.random.default_rng(0).uniform(-1, 1, (STEPS, n, env.action_size)).astype(np.float32)

    def run(qpos, qvel, actions):
        state = env.reset_to(qpos, qvel)

        def body(s, a):
            s = env.step(s, a)
            return s, (s.obs, s.reward, s.done)

        return state.obs, jax.lax.scan(body, state, actions)[1]

    obs0, (obs, reward, done) = jax.device_get(jax.jit(run)(qpos, qvel, actions))

    # Gymnasium: a reset, then the same float32 initial state (as reset_model's set_state does).
    g_obs0 = np.zeros(obs0.shape)
    g_obs, g_reward, g_done = np.zeros(obs.shape), np.zeros(reward.shape), np.zeros(done.shape, bool)
    # Gymnasium's action is the agent's [-1, 1] action mapped onto its action space.
    low, high = _gym_env(gym_id).action_space.low, _gym_env(gym_id).action_space.high
    ones = np.ones((1, env.action_size), np.float32)
    np.testing.assert_array_equal(control(env.spec, -ones, env.ctrl_range)[0], low)
    np.testing.assert_array_equal(control(env.spec, ones, env.ctrl_range)[0], high)
    ctrl = np.asarray(control(env.spec, actions, env.ctrl_range))
    for i in range(n):
        g = _gym_env(gym_id)
        g.reset(seed=i)
        g.set_state(qpos[i].astype(np.float64), qvel[i].astype(np.float64))
        g_obs0[i] = g._get_obs()
        for t in range(STEPS):
            g_obs[t, i], g_reward[t, i], g_done[t, i], truncated, _ = g.step(ctrl[t, i])
            assert not truncated

    np.testing.assert_allclose(obs0, g_obs0, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(obs, g_obs, rtol=2e-5, atol=1e-5)
    # Rewards: velocities are differences of float32 positions over dt.
    np.testing.assert_allclose(reward, g_reward, rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(done > 0.5, g_done)
    # Not vacuous: the bodies moved and the rewards vary.
    assert np.max(np.abs(obs[-1] - obs0)) > 1e-2
    assert np.std(reward) > 1e-3 or gym_id == "InvertedPendulum-v5"
    if gym_id in CONTACT_SLICE:
        forces = obs[:, :, CONTACT_SLICE[gym_id]]
        assert np.mean(np.any(forces != 0, axis=-1)) > 0.25, "contact forces are observed on many steps"


@pytest.mark.parametrize("gym_id", list(GYM_TASKS))
def test_reset_distribution_matches_gymnasium(gym_id):
    """First observations of 1000 of our resets and 1000 of Gymnasium's (seeds 0..999) come from
    the same distribution: a two-sample Kolmogorov-Smirnov test on every observation dimension
    that varies, at a family-wise level of 1e-3 (Bonferroni over the dimensions); dimensions that
    do not vary are equal. Seeds are fixed, so the test is deterministic."""
    n = 1000
    env = NativePhysics(gym_id)
    # In chunks of 100: XLA's compile time of the noise grows with the batch.
    reset = jax.jit(lambda keys: env.reset(keys).obs)
    keys = jax.random.split(jax.random.PRNGKey(7), n).reshape(10, n // 10, -1)
    ours = np.concatenate([np.asarray(reset(k), np.float64) for k in keys])
    g = _gym_env(gym_id)
    theirs = np.stack([g.reset(seed=s)[0] for s in range(n)])
    assert ours.shape == theirs.shape
    varies = np.std(theirs, axis=0) > 1e-9
    np.testing.assert_allclose(ours[:, ~varies], theirs[:, ~varies], atol=1e-6)
    assert varies.sum() >= 2
    level = 1e-3 / varies.sum()
    for d in np.nonzero(varies)[0]:
        p = stats.ks_2samp(ours[:, d], theirs[:, d]).pvalue
        assert p > level, f"dimension {d}: KS p = {p:.2e}"


def test_names_limits_and_sizes():
    """Short names and Gymnasium ids are the same tasks, with Gymnasium's sizes and time limits."""
    for short, gym_id in SHORT_NAMES.items():
        assert check_task(short) == check_task(gym_id)
        assert check_task(short).episode_length == EPISODE_LENGTH[gym_id]
        assert resolve_physics(short, "auto") == "native"
    assert check_task("reacher").episode_length == 50
    g = _gym_env("Ant-v5")
    env = VecEnv("ant", num_envs=2)
    assert (
        (env.observation_size, env.action_size)
        == (g.observation_space.shape[0], g.action_space.shape[0])
        == (105, 8)
    )
    assert VecEnv("Reacher-v5", num_envs=1).episode_length == gym.spec("Reacher-v5").max_episode_steps == 50
    assert VecEnv("hopper", num_envs=1).episode_length == gym.spec("Hopper-v5").max_episode_steps == 1000


def test_mjx_is_refused_in_one_line_with_the_reason():
    with pytest.raises(PhysicsError) as err:
        resolve_physics("humanoid", "mjx")
    msg = str(err.value)
    assert "'humanoid'" in msg and "PGS" in msg and "brax-humanoid" in msg and "\n" not in msg
    with pytest.raises(PhysicsError, match="'Humanoid-v5'.*PGS"):
        resolve_physics("Humanoid-v5", "mjx")
    for gym_id in MJX_GYM_TASKS:
        assert resolve_physics(gym_id, "mjx") == "mjx"


# MJX programs compile in 15-60 s here: the suite checks one task; COHERENT_ALL_PHYSICS=1 all.
MJX_GYM_TASKS = [g for g in GYM_TASKS if g != "Humanoid-v5"]
MJX_ALWAYS = ("InvertedPendulum-v5",)


@pytest.mark.parametrize("gym_id", MJX_GYM_TASKS)
@pytest.mark.slow
def test_mjx_runs_the_same_task_as_native_mujoco(gym_id):
    """physics=mjx steps the task's own model (Gymnasium's solver, integrator, contacts) with
    the same formulas: from the same keys and actions its first observations equal native
    MuJoCo's (which equal Gymnasium's, above), and its first steps agree to float32 accuracy
    (MJX is float32, native float64: they part slowly through contacts, as the table of matching
    steps in docs/benchmarks.md measures)."""
    if gym_id not in MJX_ALWAYS and not os.environ.get("COHERENT_ALL_PHYSICS"):
        pytest.skip("MJX compile is slow; set COHERENT_ALL_PHYSICS=1 to check every task")
    # The ant lands on its legs at its third step, where MJX's contacts part from MuJoCo C's.
    steps, n = (2 if gym_id == "Ant-v5" else 5), 2
    mjx_env, native_env = VecEnv(gym_id, n, physics="mjx").env, NativePhysics(gym_id)
    assert (mjx_env.observation_size, mjx_env.action_size) == (
        native_env.observation_size,
        native_env.action_size,
    )
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    actions = jax.random.uniform(
        jax.random.PRNGKey(1), (steps, n, native_env.action_size), minval=-1, maxval=1
    )

    def run(env, options=None):
        return jax.device_get(jax.jit(env.trajectory).lower(keys, actions).compile(options)(keys, actions))

    obs0_m, (obs_m, rew_m, done_m) = run(mjx_env, {"xla_backend_optimization_level": 0})
    obs0_n, (obs_n, rew_n, done_n) = run(native_env)
    np.testing.assert_allclose(obs0_m, obs0_n, rtol=1e-6, atol=1e-6)
    assert np.max(np.abs(obs_m - obs_n) / (1.0 + np.abs(obs_n))) < 1e-3
    np.testing.assert_allclose(rew_m, rew_n, rtol=1e-3, atol=1e-3)
    np.testing.assert_array_equal(done_m, done_n)
    assert np.isfinite(obs_m).all() and np.isfinite(rew_m).all()
    assert np.max(np.abs(obs_m[-1] - obs0_m)) > 1e-2  # not vacuous: the state moved
