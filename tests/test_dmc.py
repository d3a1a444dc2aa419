"""The DeepMind Control Suite's tasks through MuJoCo Playground (``dmc-*``)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from coherent_jax.envs import TASKS, VecEnv, check_task, make_brax_env
from coherent_jax.envs.registry import DMC_SPARSE_TASKS, dmc_name


def test_dmc_family_is_playgrounds_control_suite():
    """One ``dmc-*`` name per Playground DeepMind Control env, with Playground's time limit."""
    from mujoco_playground import registry

    ids = registry.dm_control_suite.ALL_ENVS
    assert {name for name in TASKS if name.startswith("dmc-")} == {dmc_name(i) for i in ids}
    assert dmc_name("CartpoleSwingupSparse") == "dmc-cartpole_swingup_sparse"
    assert dmc_name("BallInCup") == "dmc-ball_in_cup"
    assert set(DMC_SPARSE_TASKS) >= {
        "dmc-cartpole_swingup_sparse",
        "dmc-acrobot_swingup_sparse",
        "dmc-ball_in_cup",
        "dmc-finger_turn_hard",
    }
    for i in ids:
        spec = check_task(dmc_name(i))
        assert spec.playground_id == i
        cfg = registry.get_default_config(i)
        assert spec.episode_length * cfg.action_repeat == cfg.episode_length, i
        assert spec.backend == "mjx"


@pytest.mark.slow
def test_dmc_task_under_the_vectorized_wrapper():
    """Playground's env under the vectorized wrapper, jitted: the reset is Playground's
    reset from the wrapper's keys, actions are clipped to [-1, 1], the sparse reward is 0
    or 1, nothing terminates, and the time limit truncates with the pre-reset observation
    kept and a fresh initial state drawn.

    Compiled for a check of the wrapper, not for speed (XLA's backend optimisation off):
    Playground's import, MJX's tracing and the compile are 10-20 s each on this CPU."""
    name, n, limit = "dmc-cartpole_swingup_sparse", 2, 3
    env = VecEnv(name, num_envs=n, episode_length=limit)
    raw = make_brax_env(name)
    assert (env.observation_size, env.action_size, env.dt) == (5, 1, pytest.approx(0.01))
    # Beyond the actuator's range, to see the clipping.
    actions = jnp.array([3.0, -3.0, 0.5, 1.0])[:, None, None] * jnp.ones((1, n, 1))

    def run(key):
        def body(state, a):
            state, out = env.step(state, a)
            return state, (state, out)

        state = env.reset(key)
        return state, *jax.lax.scan(body, state, actions)[1]

    key = jax.random.PRNGKey(0)
    compiled = jax.jit(run).lower(key).compile({"xla_backend_optimization_level": 0})
    state0, states, outcomes = jax.tree.map(np.asarray, compiled(key))
    # Playground's own reset from the keys the wrapper's first reset uses (eval_shape:
    # traced, not compiled again) has the same structure; its first observation is the
    # initial pose's: the cart near 0 and the pole hanging down (cos = -1), within 6 sigma.
    ref = jax.eval_shape(jax.vmap(raw.reset), jax.random.split(jax.random.split(key)[1], n))
    assert jax.tree.structure(ref) == jax.tree.structure(jax.tree.map(jnp.asarray, state0.physics))
    np.testing.assert_allclose(state0.obs[:, :3], [[0.0, -1.0, 0.0]] * n, atol=0.06)  # noise 0.01 N(0, 1)
    # The clipped action moved the cart as +1 and -1 would: the cart velocity (obs 3)
    # after the first two steps has the sign of the clipped action.
    assert (states.obs[0, :, 3] > 0).all() and (states.obs[1, :, 3] < states.obs[0, :, 3]).all()
    assert set(np.unique(outcomes.reward)) <= {0.0, 1.0}
    assert not outcomes.terminated.any()
    np.testing.assert_array_equal(outcomes.truncated[:, 0], [False, False, True, False])
    np.testing.assert_array_equal(outcomes.final_obs[: limit - 1], states.obs[: limit - 1])
    assert states.first[limit - 1].all() and (states.step[limit - 1] == 0).all()
    # The reset after the time limit is a fresh draw, not the first state replayed.
    assert not np.array_equal(states.obs[limit - 1], state0.obs)
    assert not np.array_equal(outcomes.final_obs[limit - 1], states.obs[limit - 1])


def _playground_formulas(task: str, qpos, mocap=None):
    """(obs, reward) of our native task's formulas and of Playground's own, on identical states.

    Each state is MuJoCo's forward pass at ``qpos`` (zero velocity; the mocap bodies at
    ``mocap``); ours read its `Kinematics` fields, Playground's ``_get_obs`` and
    ``_get_reward`` read the same MjData handed to MJX with ``mjx.put_data`` (indexing and
    arithmetic, run eagerly)."""
    import mujoco
    from mujoco import mjx

    from coherent_jax.envs.mujoco_task import Kinematics
    from coherent_jax.envs.physics import NATIVE_TASKS

    spec, raw = NATIVE_TASKS[task], make_brax_env(task)
    model = spec.load().model
    data = mujoco.MjData(model)
    ours, theirs = [], []
    for i in range(len(qpos)):
        mujoco.mj_resetData(model, data)
        data.qpos[:] = qpos[i]
        if mocap is not None:
            data.mocap_pos[:] = mocap[i]
        mujoco.mj_forward(model, data)
        kin = Kinematics(**{f: jnp.asarray(getattr(data, f), jnp.float32) for f in spec.fields})
        ours.append((np.asarray(spec.observe(kin)), float(spec.reward_done(kin, kin, None, 0.0)[0])))
        d = mjx.put_data(model, data)
        theirs.append((np.asarray(raw._get_obs(d, {})), float(raw._get_reward(d, None, {}, {}))))
    return tuple([np.stack(v) for v in zip(*pairs, strict=True)] for pairs in (ours, theirs))


def test_native_dmc_formulas_are_playgrounds_on_identical_states():
    """Native ball-in-cup and finger-turn compute Playground's observation and sparse reward
    (float32 against Playground's own functions on the same MuJoCo state), on grids of
    states where the reward is both 0 and 1: the ball swept through the cup, the hinged
    body turned past the target through a full turn."""
    grid = np.stack(np.meshgrid(np.linspace(-0.06, 0.06, 7), np.linspace(0.3, 0.4, 7)), -1).reshape(-1, 2)
    qpos = np.zeros((len(grid), 4))
    qpos[:, 2:] = grid  # ball_x, ball_z; the cup stays at its origin
    (obs, reward), (ref_obs, ref_reward) = _playground_formulas("dmc-ball_in_cup", qpos)
    np.testing.assert_allclose(obs, ref_obs, atol=1e-6)
    np.testing.assert_array_equal(reward, ref_reward)
    assert 0 < reward.sum() < len(reward)

    from coherent_jax.envs.native_ports import _finger_layout

    lay = _finger_layout("FingerTurnHard")
    turn = np.linspace(-np.pi, np.pi, 91)
    qpos = np.zeros((len(turn), 3))
    qpos[:, 0], qpos[:, 1], qpos[:, 2] = 0.3, -0.4, turn  # the finger off the body
    mocap = np.broadcast_to(lay.mocap_pos, (len(turn), *lay.mocap_pos.shape)).copy()
    mocap[:, lay.mocap, 0] = lay.hinge[0] + lay.radius * np.sin(1.0)  # the target at angle 1
    mocap[:, lay.mocap, 2] = lay.hinge[2] + lay.radius * np.cos(1.0)
    (obs, reward), (ref_obs, ref_reward) = _playground_formulas("dmc-finger_turn_hard", qpos, mocap)
    np.testing.assert_allclose(obs, ref_obs, atol=2e-6)
    np.testing.assert_array_equal(reward, ref_reward)
    assert 0 < reward.sum() < len(reward)


@pytest.mark.parametrize("task", ["dmc-ball_in_cup", "dmc-finger_turn_hard"])
def test_native_dmc_steps_match_playground_side_by_side(task):
    """From the same keys (the same initial state, the finger's target included) and
    actions, native MuJoCo and Playground's MJX env give the same observations (relative
    1e-3), rewards and terminations for the first steps, which move the state."""
    import os

    from helpers import native_and_mjx_rollouts

    if not os.environ.get("COHERENT_ALL_PHYSICS"):
        pytest.skip("MJX compile is slow; set COHERENT_ALL_PHYSICS=1 to step Playground's env")
    steps = 8
    mjx, native = native_and_mjx_rollouts(task, 2, steps)
    (obs0_m, (obs_m, rew_m, done_m)), (obs0_n, (obs_n, rew_n, done_n)) = mjx, native
    np.testing.assert_allclose(np.asarray(obs0_n), np.asarray(obs0_m), atol=1e-6)
    scale = 1.0 + np.abs(np.asarray(obs_m))
    assert np.max(np.abs(np.asarray(obs_n) - np.asarray(obs_m)) / scale) < 1e-3
    np.testing.assert_array_equal(np.asarray(rew_n), np.asarray(rew_m))
    np.testing.assert_array_equal(np.asarray(done_n), np.asarray(done_m))
    assert np.max(np.abs(np.asarray(obs_m[-1]) - np.asarray(obs0_m))) > 1e-2
