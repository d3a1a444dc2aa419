"""Gymnasium's MuJoCo v5 tasks, as `NativeTask`s: the tasks papers report returns on.

Each task loads its own MJCF from the installed ``gymnasium`` package (so its
integrator, solver, contacts and timestep are Gymnasium's), steps ``frame_skip``
substeps per env step, and computes observation, reward and termination with the
formulas and default weights of Gymnasium 1.4.0's ``*_v5.py`` classes, written here in
JAX. Observations are float32 (Gymnasium's are float64); the physics state itself stays
float64, so trajectories are the same as Gymnasium's.

The agent acts in [-1, 1]; the action is mapped affinely onto the actuators'
ctrlrange, which is Gymnasium's action space, and the control cost is taken on the
mapped action, as Gymnasium takes it on the action it receives.
"""

from __future__ import annotations

import functools
import importlib.util
import os

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from coherent_jax.envs.mujoco_task import Kinematics, NativeModel, NativeTask, uniform_reset
from coherent_jax.envs.quiet import quiet_stdio
from coherent_jax.envs.registry import EPISODE_LENGTH, SHORT_NAMES  # noqa: F401  (re-exported)


class GymnasiumMissingError(ImportError):
    """Gymnasium's tasks need the ``gymnasium`` package for their MJCF files."""


def _assets_dir() -> str:
    # The MJCF files only: importing gymnasium.envs.mujoco would pull in its renderer.
    spec = importlib.util.find_spec("gymnasium")
    if spec is None or not spec.submodule_search_locations:
        raise GymnasiumMissingError(
            "Gymnasium's MuJoCo tasks load their MJCF files from the gymnasium package: "
            'pip install -e ".[gym]"'
        )
    return os.path.join(spec.submodule_search_locations[0], "envs", "mujoco", "assets")


@functools.cache
def load_model(xml: str, frame_skip: int) -> NativeModel:
    """Gymnasium's model `xml` as its ``MujocoEnv`` builds it; init_q is the model's qpos0."""
    # The compiler warns that settotalmass (half_cheetah.xml, humanoid.xml) is deprecated, on
    # stdout and, unless a handler is set, into MUJOCO_LOG.TXT in the working directory.
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda message: None)
    try:
        with quiet_stdio(force=True):
            model = mujoco.MjModel.from_xml_path(os.path.join(_assets_dir(), xml))
    finally:
        mujoco.set_mju_user_warning(previous)
    init_q = np.asarray(mujoco.MjData(model).qpos, np.float32)
    return NativeModel(model, int(frame_skip), float(model.opt.timestep * frame_skip), init_q)


def _ctrl_cost(weight: float, ctrl: jax.Array) -> jax.Array:
    return weight * jnp.sum(jnp.square(ctrl))


def _never(reward: jax.Array) -> tuple[jax.Array, jax.Array]:
    return reward, jnp.zeros(())


# --- HalfCheetah-v5: r = vx - 0.1 |a|^2, x = qpos[0]; never terminates.
def _half_cheetah_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate([k.qpos[1:], k.qvel])


def _half_cheetah_reward(k0: Kinematics, k1: Kinematics, ctrl: jax.Array, dt: float):
    return _never((k1.qpos[0] - k0.qpos[0]) / dt - _ctrl_cost(0.1, ctrl))


# --- Hopper-v5 and Walker2d-v5: r = vx + 1[healthy] - 1e-3 |a|^2; done = not healthy.
def _planar_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate([k.qpos[1:], jnp.clip(k.qvel, -10.0, 10.0)])


def _planar_reward(healthy, k0: Kinematics, k1: Kinematics, ctrl: jax.Array, dt: float):
    ok = healthy(k1)
    reward = (k1.qpos[0] - k0.qpos[0]) / dt + ok.astype(jnp.float32) - _ctrl_cost(1e-3, ctrl)
    return reward, 1.0 - ok.astype(jnp.float32)


def _hopper_healthy(k: Kinematics) -> jax.Array:
    """|(qpos, qvel)[2:]| < 100, z = qpos[1] > 0.7, |angle = qpos[2]| < 0.2 (all strict)."""
    z, angle = k.qpos[1], k.qpos[2]
    state = jnp.concatenate([k.qpos, k.qvel])[2:]
    return jnp.all((state > -100.0) & (state < 100.0)) & (z > 0.7) & (z < jnp.inf) & (jnp.abs(angle) < 0.2)


def _walker_healthy(k: Kinematics) -> jax.Array:
    """0.8 < z = qpos[1] < 2, -1 < angle = qpos[2] < 1."""
    z, angle = k.qpos[1], k.qpos[2]
    return (z > 0.8) & (z < 2.0) & (angle > -1.0) & (angle < 1.0)


# --- Ant-v5: contact forces clipped to [-1, 1] enter the observation and a contact cost.
def _ant_contact(k: Kinematics) -> jax.Array:
    return jnp.clip(k.cfrc_ext, -1.0, 1.0)


def _ant_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate([k.qpos[2:], k.qvel, _ant_contact(k)[1:].ravel()])


def _ant_reward(k0: Kinematics, k1: Kinematics, ctrl: jax.Array, dt: float):
    """r = vx(torso) + 1[healthy] - 0.5 |a|^2 - 5e-4 |clip(cfrc_ext)|^2; healthy: finite, 0.2 <= z <= 1."""
    z = k1.qpos[2]
    healthy = jnp.all(jnp.isfinite(k1.qpos)) & jnp.all(jnp.isfinite(k1.qvel)) & (z >= 0.2) & (z <= 1.0)
    vx = (k1.xpos[1, 0] - k0.xpos[1, 0]) / dt
    contact_cost = 5e-4 * jnp.sum(jnp.square(_ant_contact(k1)))
    reward = vx + healthy.astype(jnp.float32) - _ctrl_cost(0.5, ctrl) - contact_cost
    return reward, 1.0 - healthy.astype(jnp.float32)


# --- Humanoid-v5: the mass centre moves forward; contact cost capped at 10.
def _humanoid_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate(
        [
            k.qpos[2:],
            k.qvel,
            k.cinert[1:].ravel(),
            k.cvel[1:].ravel(),
            k.qfrc_actuator[6:],
            k.cfrc_ext[1:].ravel(),
        ]
    )


def _mass_centre_x(k: Kinematics) -> jax.Array:
    mass = jnp.asarray(load_model("humanoid.xml", 5).model.body_mass, jnp.float32)
    return jnp.sum(mass * k.xipos[:, 0]) / jnp.sum(mass)


def _humanoid_reward(k0: Kinematics, k1: Kinematics, ctrl: jax.Array, dt: float):
    """r = 1.25 vx(mass centre) + 5 1[healthy] - 0.1 |a|^2 - min(5e-7 |cfrc_ext|^2, 10);
    healthy: 1 < z < 2."""
    healthy = (k1.qpos[2] > 1.0) & (k1.qpos[2] < 2.0)
    vx = (_mass_centre_x(k1) - _mass_centre_x(k0)) / dt
    contact_cost = jnp.minimum(5e-7 * jnp.sum(jnp.square(k1.cfrc_ext)), 10.0)
    reward = 1.25 * vx + 5.0 * healthy.astype(jnp.float32) - _ctrl_cost(0.1, ctrl) - contact_cost
    return reward, 1.0 - healthy.astype(jnp.float32)


# --- Swimmer-v5: r = vx - 1e-4 |a|^2, x = qpos[0]; never terminates.
def _swimmer_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate([k.qpos[2:], k.qvel])


def _swimmer_reward(k0: Kinematics, k1: Kinematics, ctrl: jax.Array, dt: float):
    return _never((k1.qpos[0] - k0.qpos[0]) / dt - _ctrl_cost(1e-4, ctrl))


# --- InvertedPendulum-v5: r = 1 while the pole stands, 0 on the step it falls.
def _pendulum_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate([k.qpos, k.qvel])


def _pendulum_reward(k0: Kinematics, k1: Kinematics, ctrl: jax.Array, dt: float):
    """done: a non-finite observation or |pole angle = qpos[1]| > 0.2."""
    obs = _pendulum_obs(k1)
    done = ~jnp.all(jnp.isfinite(obs)) | (jnp.abs(obs[1]) > 0.2)
    return 1.0 - done.astype(jnp.float32), done.astype(jnp.float32)


# --- InvertedDoublePendulum-v5: the tip site's height; the first constraint force is observed.
def _double_pendulum_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate(
        [
            k.qpos[:1],
            jnp.sin(k.qpos[1:]),
            jnp.cos(k.qpos[1:]),
            jnp.clip(k.qvel, -10.0, 10.0),
            jnp.clip(k.qfrc_constraint, -10.0, 10.0)[:1],
        ]
    )


def _double_pendulum_reward(k0: Kinematics, k1: Kinematics, ctrl: jax.Array, dt: float):
    """(x, y) = tip site (x, z); done: y <= 1;
    r = 10 (1 - done) - 0.01 x^2 - (y - 2)^2 - 1e-3 v1^2 - 5e-3 v2^2."""
    x, y = k1.site_xpos[0, 0], k1.site_xpos[0, 2]
    v1, v2 = k1.qvel[1], k1.qvel[2]
    done = (y <= 1.0).astype(jnp.float32)
    reward = 10.0 * (1.0 - done) - (0.01 * x**2 + (y - 2.0) ** 2) - (1e-3 * v1**2 + 5e-3 * v2**2)
    return reward, done


# --- Reacher-v5: bodies 3 and 4 are the fingertip and the target.
_FINGERTIP, _TARGET = 3, 4


def _reacher_obs(k: Kinematics) -> jax.Array:
    theta = k.qpos[:2]
    to_target = k.xpos[_FINGERTIP] - k.xpos[_TARGET]
    return jnp.concatenate([jnp.cos(theta), jnp.sin(theta), k.qpos[2:], k.qvel[:2], to_target[:2]])


def _reacher_reward(k0: Kinematics, k1: Kinematics, ctrl: jax.Array, dt: float):
    """r = -|fingertip - target| - |a|^2, after the step; never terminates."""
    distance = jnp.linalg.norm(k1.xpos[_FINGERTIP] - k1.xpos[_TARGET])
    return _never(-distance - _ctrl_cost(1.0, ctrl))


def _reacher_reset(key: jax.Array, init_q: jax.Array, nv: int) -> tuple[jax.Array, jax.Array]:
    """Arm q0 + U(-0.1, 0.1), target uniform in the disc of radius 0.2 (rejection sampling from
    the square, as Gymnasium draws it), arm velocity U(-0.005, 0.005), target at rest."""
    k_q, k_goal, k_qd = jax.random.split(key, 3)
    q = init_q + jax.random.uniform(k_q, init_q.shape, minval=-0.1, maxval=0.1)

    def draw(carry):
        key, _ = carry
        key, sub = jax.random.split(key)
        return key, jax.random.uniform(sub, (2,), minval=-0.2, maxval=0.2)

    _, goal = jax.lax.while_loop(
        lambda carry: jnp.linalg.norm(carry[1]) >= 0.2, draw, draw((k_goal, jnp.zeros(2)))
    )
    qd = jax.random.uniform(k_qd, (nv,), minval=-0.005, maxval=0.005)
    return q.at[-2:].set(goal), qd.at[-2:].set(0.0)


def _task(xml, frame_skip, fields, reset_noise, observe, reward_done) -> NativeTask:
    return NativeTask(
        load=functools.partial(load_model, xml, frame_skip),
        fields=fields,
        reset_noise=reset_noise,
        observe=observe,
        reward_done=reward_done,
        scale_action=True,
        normalize_quaternions=False,
        source="Gymnasium 1.4.0",
    )


_QV = ("qpos", "qvel")

GYM_TASKS: dict[str, NativeTask] = {
    "HalfCheetah-v5": _task(
        "half_cheetah.xml", 5, _QV, uniform_reset(0.1, 0.1, True), _half_cheetah_obs, _half_cheetah_reward
    ),
    "Hopper-v5": _task(
        "hopper.xml",
        4,
        _QV,
        uniform_reset(5e-3, 5e-3, False),
        _planar_obs,
        functools.partial(_planar_reward, _hopper_healthy),
    ),
    "Walker2d-v5": _task(
        "walker2d_v5.xml",
        4,
        _QV,
        uniform_reset(5e-3, 5e-3, False),
        _planar_obs,
        functools.partial(_planar_reward, _walker_healthy),
    ),
    "Ant-v5": _task(
        "ant.xml", 5, (*_QV, "xpos", "cfrc_ext"), uniform_reset(0.1, 0.1, True), _ant_obs, _ant_reward
    ),
    "Humanoid-v5": _task(
        "humanoid.xml",
        5,
        (*_QV, "xipos", "cinert", "cvel", "qfrc_actuator", "cfrc_ext"),
        uniform_reset(0.01, 0.01, False),
        _humanoid_obs,
        _humanoid_reward,
    ),
    "Swimmer-v5": _task("swimmer.xml", 4, _QV, uniform_reset(0.1, 0.1, False), _swimmer_obs, _swimmer_reward),
    "InvertedPendulum-v5": _task(
        "inverted_pendulum.xml", 2, _QV, uniform_reset(0.01, 0.01, False), _pendulum_obs, _pendulum_reward
    ),
    "InvertedDoublePendulum-v5": _task(
        "inverted_double_pendulum.xml",
        5,
        (*_QV, "site_xpos", "qfrc_constraint"),
        uniform_reset(0.1, 0.1, True),
        _double_pendulum_obs,
        _double_pendulum_reward,
    ),
    "Reacher-v5": _task("reacher.xml", 2, (*_QV, "xpos"), _reacher_reset, _reacher_obs, _reacher_reward),
}
