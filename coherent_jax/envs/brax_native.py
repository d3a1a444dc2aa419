"""Six of Brax's MJX re-creations (``brax-*``) as `NativeTask`s, for native MuJoCo.

The same task as its MJX version: the ``MjModel`` Brax builds, with the MJX task's
solver options (``TaskSpec.ls_iterations`` and Brax's own overrides, such as ant's
Newton solver with one iteration) copied onto it, the same substeps, the same reset
noise drawn from the same JAX keys, and the formulas of Brax 0.14.2's env classes
(``brax/envs/<task>.py``), written here in JAX. `coherent_jax.envs.physics` steps them.
"""

from __future__ import annotations

import copy
import functools

import jax
import jax.numpy as jnp
import numpy as np

from coherent_jax.envs.brax_env import make_brax_env
from coherent_jax.envs.mujoco_task import Kinematics, NativeModel, NativeTask, quat_rotate, uniform_reset


# --- Brax's tasks (Brax 0.14.2, brax/envs/<task>.py; `dt` is the env step). Body 1 is the torso.
def _halfcheetah_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate([k.qpos[1:], k.qvel])


def _halfcheetah_reward(k0: Kinematics, k1: Kinematics, action: jax.Array, dt: float):
    """r = (x_torso' - x_torso) / dt - 0.1 |a|^2; never terminates."""
    reward = (k1.xpos[1, 0] - k0.xpos[1, 0]) / dt - 0.1 * jnp.sum(jnp.square(action))
    return reward, jnp.zeros(())


def _inverted_pendulum_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate([k.qpos, k.qvel])


def _inverted_pendulum_reward(k0: Kinematics, k1: Kinematics, action: jax.Array, dt: float):
    """r = 1; done when the pole angle |q_1| > 0.2."""
    return jnp.ones(()), (jnp.abs(k1.qpos[1]) > 0.2).astype(jnp.float32)


def _planar_obs(k: Kinematics) -> jax.Array:
    """Hopper and walker2d: q with q_1 replaced by the torso height, x dropped; qd clipped to [-10, 10]."""
    position = k.qpos.at[1].set(k.xpos[1, 2])[1:]
    return jnp.concatenate([position, jnp.clip(k.qvel, -10.0, 10.0)])


def _hopper_reward(k0: Kinematics, k1: Kinematics, action: jax.Array, dt: float):
    """r = vx + 1 - 1e-3 |a|^2; healthy: |(q_2:, qd)| < 100, z > 0.7, |angle| < 0.2."""
    z, angle = k1.xpos[1, 2], k1.qpos[2]
    state_vec = jnp.concatenate([k1.qpos[2:], k1.qvel])
    healthy = jnp.all((state_vec > -100.0) & (state_vec < 100.0)) & (z > 0.7) & (angle > -0.2) & (angle < 0.2)
    reward = (k1.xpos[1, 0] - k0.xpos[1, 0]) / dt + 1.0 - 1e-3 * jnp.sum(jnp.square(action))
    return reward, 1.0 - healthy.astype(jnp.float32)


def _walker2d_reward(k0: Kinematics, k1: Kinematics, action: jax.Array, dt: float):
    """r = vx + 1 - 1e-3 |a|^2; healthy: 0.8 < z < 2, -1 < angle < 1."""
    z, angle = k1.xpos[1, 2], k1.qpos[2]
    healthy = (z > 0.8) & (z < 2.0) & (angle > -1.0) & (angle < 1.0)
    reward = (k1.xpos[1, 0] - k0.xpos[1, 0]) / dt + 1.0 - 1e-3 * jnp.sum(jnp.square(action))
    return reward, 1.0 - healthy.astype(jnp.float32)


def _ant_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate([k.qpos[2:], k.qvel])


def _ant_reward(k0: Kinematics, k1: Kinematics, action: jax.Array, dt: float):
    """r = vx + 1 - 0.5 |a|^2 (no contact cost); healthy: 0.2 <= z_torso <= 1."""
    z = k1.xpos[1, 2]
    healthy = (z >= 0.2) & (z <= 1.0)
    reward = (k1.xpos[1, 0] - k0.xpos[1, 0]) / dt + 1.0 - 0.5 * jnp.sum(jnp.square(action))
    return reward, 1.0 - healthy.astype(jnp.float32)


def _double_pendulum_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate(
        [k.qpos[:1], jnp.sin(k.qpos[1:]), jnp.cos(k.qpos[1:]), jnp.clip(k.qvel, -10.0, 10.0)]
    )


def _double_pendulum_reward(k0: Kinematics, k1: Kinematics, action: jax.Array, dt: float):
    """Tip = pole2 frame (body 3) applied to (0, 0, 0.6); done when tip y <= 1;
    r = 10 (1 - done) - 0.01 x^2 - (y - 2)^2 - 1e-3 v1^2 - 5e-3 v2^2."""
    tip = k1.xpos[3] + quat_rotate(k1.xquat[3], jnp.array([0.0, 0.0, 0.6]))
    x, y = tip[0], tip[2]
    v1, v2 = k1.qvel[1], k1.qvel[2]
    done = (y <= 1.0).astype(jnp.float32)
    reward = (1.0 - done) * 10.0 - (0.01 * x**2 + (y - 2.0) ** 2) - (1e-3 * v1**2 + 5e-3 * v2**2)
    return reward, done


@functools.cache
def _brax_model(brax_task: str) -> NativeModel:
    """The ``MjModel`` Brax builds for `brax_task`, with the solver options its MJX task uses.

    Brax builds its ``System`` from an ``MjModel`` and then replaces options on the
    ``System`` only (``TaskSpec.ls_iterations``, ant's Newton solver, ...): copy them back.
    """
    env = make_brax_env(brax_task)
    model = copy.deepcopy(env.sys.mj_model)
    opt = env.sys.opt
    for name in (
        "timestep",
        "iterations",
        "ls_iterations",
        "tolerance",
        "ls_tolerance",
        "impratio",
        "gravity",
        "density",
        "viscosity",
        "magnetic",
        "wind",
    ):
        setattr(model.opt, name, np.asarray(getattr(opt, name)))
    for name in ("jacobian", "cone", "disableflags", "enableflags", "integrator", "solver"):
        setattr(model.opt, name, int(getattr(opt, name)))
    # Brax's initial pose (``sys.init_q``, e.g. ant's first keyframe), not the model's qpos0.
    return NativeModel(model, int(env._n_frames), float(env.dt), np.asarray(env.sys.init_q, np.float32))


def _brax_task(name, reset_noise, observe, reward_done, scale_action=False) -> NativeTask:
    return NativeTask(
        load=functools.partial(_brax_model, f"brax-{name}"),
        fields=("qpos", "qvel", "xpos", "xquat"),
        reset_noise=reset_noise,
        observe=observe,
        reward_done=reward_done,
        scale_action=scale_action,  # Brax's inverted_pendulum maps [-1, 1] onto its ctrlrange
        brax_scaling=True,
        normalize_quaternions=True,
        source="Brax 0.14.2",
    )


BRAX_NATIVE: dict[str, NativeTask] = {
    "brax-halfcheetah": _brax_task(
        "halfcheetah", uniform_reset(0.1, 0.1, True), _halfcheetah_obs, _halfcheetah_reward
    ),
    "brax-inverted_pendulum": _brax_task(
        "inverted_pendulum",
        uniform_reset(0.01, 0.01, False),
        _inverted_pendulum_obs,
        _inverted_pendulum_reward,
        scale_action=True,
    ),
    "brax-hopper": _brax_task("hopper", uniform_reset(5e-3, 5e-3, False), _planar_obs, _hopper_reward),
    "brax-walker2d": _brax_task("walker2d", uniform_reset(5e-3, 5e-3, False), _planar_obs, _walker2d_reward),
    "brax-ant": _brax_task("ant", uniform_reset(0.1, 0.1, True), _ant_obs, _ant_reward),
    "brax-inverted_double_pendulum": _brax_task(
        "inverted_double_pendulum",
        uniform_reset(0.01, 0.01, True),
        _double_pendulum_obs,
        _double_pendulum_reward,
    ),
}
