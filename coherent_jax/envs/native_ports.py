"""Tasks of the MJX libraries, Brax's and MuJoCo Playground's, ported to native MuJoCo as
`NativeTask`s: the same task as its MJX version (the model the library builds, its substeps,
the same reset drawn from the same JAX keys, its formulas written here in JAX), stepped by
MuJoCo's C engine (`coherent_jax.envs.physics`). The library's env is built once per task
(`coherent_jax.envs.brax_env`) for its model.

**Brax** (``BRAX_NATIVE``): six of Brax's MJX re-creations (``brax-*``). The ``MjModel`` Brax
builds, with the MJX task's solver options (``TaskSpec.ls_iterations`` and Brax's own
overrides, such as ant's Newton solver with one iteration) copied onto it, the same
substeps, the same reset noise drawn from the same JAX keys, and the formulas of Brax
0.14.2's env classes (``brax/envs/<task>.py``).

**MuJoCo Playground** (``DMC_NATIVE``): two DeepMind Control tasks, the ones MJX runs slowest
on a CPU. Playground's MJX ports of ball-in-cup and finger-turn are the contact-rich tasks
of the sparse suite. MuJoCo's C engine runs them faster on a CPU: in PPO with action
noise (64 envs x 64 steps, the first 61,440 steps of a run) 19.2k env steps/s against
11.9k on MJX for ball-in-cup, 25.3k against 17.3k for finger turn hard
(``python -m benchmarks physics env=dmc-ball_in_cup`` times the physics alone).
Each task here is Playground 0.2.0's, written as a `NativeTask`:

* the ``MjModel`` Playground builds (its MJCF and assets, its timestep, the finger's
  target radius), with Playground's substeps per env step;
* the same reset drawn from the same JAX keys, including the order of Playground's key
  splits and its quirks (the finger's target is placed after the forward pass, so the
  first observation reads the target sensor at the model's default target);
* observation, reward and termination (NaN in the state) from the same MjData fields
  with Playground's formulas, written below.

MJX and MuJoCo C resolve contacts with different arithmetic, so the two engines run the
same task, not the same trajectories: `tests/test_dmc.py` checks equal first steps and
equal formulas on identical states.
"""

from __future__ import annotations

import copy
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from coherent_jax.envs.brax_env import make_brax_env, make_playground_env
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


# --- MuJoCo Playground's DeepMind Control tasks (Playground 0.2.0)
@functools.cache
def _playground_env(playground_id: str):
    return make_playground_env(playground_id)


@functools.cache
def load_model(playground_id: str) -> NativeModel:
    """Playground's own ``MjModel`` of the task, its substeps and control step."""
    env = _playground_env(playground_id)
    model = env.mj_model
    return NativeModel(model, int(env.n_substeps), float(env.dt), np.asarray(model.qpos0, np.float32))


def _nan_done(k: Kinematics) -> jax.Array:
    """Playground's termination: a NaN anywhere in qpos or qvel."""
    return (jnp.any(jnp.isnan(k.qpos)) | jnp.any(jnp.isnan(k.qvel))).astype(jnp.float32)


# --- BallInCup: a fixed initial state; reward 1 while the ball's (x, z) is inside the
# target box (half-sizes minus the ball's radius) at the cup.
class _CupLayout(NamedTuple):
    ball_body: int
    target_site: int
    inner: np.ndarray  # [2] target half-sizes (x, z) minus the ball radius


@functools.cache
def _cup_layout() -> _CupLayout:
    model = load_model("BallInCup").model
    target = model.site("target").id
    inner = model.site_size[target, [0, 2]] - model.geom_size[model.geom("ball").id, 0]
    return _CupLayout(model.body("ball").id, target, np.asarray(inner, np.float32))


def _cup_reset(key: jax.Array, init_q: jax.Array, nv: int) -> tuple[jax.Array, jax.Array]:
    del key  # Playground's BallInCup starts every episode at the model's qpos0
    return init_q, jnp.zeros((nv,), init_q.dtype)


def _cup_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate([k.qpos, k.qvel])


def _cup_reward(k0: Kinematics, k1: Kinematics, ctrl: jax.Array, dt: float):
    del k0, ctrl, dt
    lay = _cup_layout()
    xz = jnp.array([0, 2])
    gap = jnp.abs(k1.site_xpos[lay.target_site, xz] - k1.xpos[lay.ball_body, xz])
    return jnp.prod(jnp.where(gap < lay.inner, 1.0, 0.0)), _nan_done(k1)


# --- FingerTurnHard: the finger's two joints and the hinged body's angle uniform, the
# target on the body's tip circle at a uniform angle; reward 1 while the tip is inside
# the target (signed distance <= 0). Observations are sensor readings.
class _FingerLayout(NamedTuple):
    sensors: dict  # name -> (address, dim) in sensordata
    lowers: np.ndarray  # [2] ranges of the finger's joints
    uppers: np.ndarray
    hinge: np.ndarray  # [3] the hinge's anchor (fixed in the world)
    radius: float  # the tip circle's radius
    target_size: float
    mocap: int  # the target body's mocap index
    mocap_pos: np.ndarray  # [nmocap, 3] the model's default mocap positions


@functools.cache
def _finger_layout(playground_id: str) -> _FingerLayout:
    model = load_model(playground_id).model
    adr, dim = model.sensor_adr, model.sensor_dim
    sensors = {model.sensor(i).name: (int(adr[i]), int(dim[i])) for i in range(model.nsensor)}
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    hinge = data.xanchor[model.joint("hinge").id].astype(np.float32)
    return _FingerLayout(
        sensors=sensors,
        lowers=np.asarray(model.jnt_range[:2, 0], np.float32),
        uppers=np.asarray(model.jnt_range[:2, 1], np.float32),
        hinge=hinge,
        radius=float(model.geom("cap1").size.sum()),
        target_size=float(model.site("target").size[0]),
        mocap=int(model.body("target").mocapid[0]),
        mocap_pos=np.asarray(data.mocap_pos, np.float32),
    )


def _sensor(k: Kinematics, lay: _FingerLayout, name: str) -> jax.Array:
    adr, dim = lay.sensors[name]
    return k.sensordata[adr : adr + dim]


def _finger_reset(playground_id: str):
    def reset(key: jax.Array, init_q: jax.Array, nv: int):
        lay = _finger_layout(playground_id)
        _, k_pose, k_target = jax.random.split(key, 3)
        qpos = jnp.zeros_like(init_q)
        qpos = qpos.at[:2].set(jax.random.uniform(k_pose, (2,), minval=lay.lowers, maxval=lay.uppers))
        qpos = qpos.at[2].set(jax.random.uniform(k_pose, minval=-jnp.pi, maxval=jnp.pi))
        angle = jax.random.uniform(k_target, minval=-jnp.pi, maxval=jnp.pi)
        mocap = jnp.asarray(lay.mocap_pos)
        target = mocap[lay.mocap]
        target = target.at[0].set(lay.hinge[0] + lay.radius * jnp.sin(angle))
        target = target.at[2].set(lay.hinge[2] + lay.radius * jnp.cos(angle))
        return qpos, jnp.zeros((nv,), init_q.dtype), mocap.at[lay.mocap].set(target)

    return reset


def _finger_target(k: Kinematics, lay: _FingerLayout) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(tip, target) (x, z) relative to the spinner, and the tip's signed distance to the
    target's surface (negative inside)."""
    xz = jnp.array([0, 2])
    spinner = _sensor(k, lay, "spinner")[xz]
    tip = _sensor(k, lay, "tip")[xz] - spinner
    target = _sensor(k, lay, "target")[xz] - spinner
    return tip, target, jnp.linalg.norm(target - tip) - lay.target_size


def _finger_obs(playground_id: str):
    def observe(k: Kinematics) -> jax.Array:
        lay = _finger_layout(playground_id)
        tip, target, dist = _finger_target(k, lay)
        touch = jnp.log1p(jnp.concatenate([_sensor(k, lay, "touchtop"), _sensor(k, lay, "touchbottom")]))
        return jnp.concatenate(
            [_sensor(k, lay, "proximal"), _sensor(k, lay, "distal"), tip, k.qvel, touch, target, dist[None]]
        )

    return observe


def _finger_reward(playground_id: str):
    def reward_done(k0: Kinematics, k1: Kinematics, ctrl: jax.Array, dt: float):
        del k0, ctrl, dt
        _, _, dist = _finger_target(k1, _finger_layout(playground_id))
        return jnp.where(dist <= 0.0, 1.0, 0.0), _nan_done(k1)

    return reward_done


def _task(playground_id, fields, reset_noise, observe, reward_done) -> NativeTask:
    return NativeTask(
        load=functools.partial(load_model, playground_id),
        fields=fields,
        reset_noise=reset_noise,
        observe=observe,
        reward_done=reward_done,
        source="MuJoCo Playground 0.2.0",
    )


# By registry name (``dmc-*``).
DMC_NATIVE: dict[str, NativeTask] = {
    "dmc-ball_in_cup": _task(
        "BallInCup", ("qpos", "qvel", "xpos", "site_xpos"), _cup_reset, _cup_obs, _cup_reward
    ),
    "dmc-finger_turn_hard": _task(
        "FingerTurnHard",
        ("qpos", "qvel", "sensordata"),
        _finger_reset("FingerTurnHard"),
        _finger_obs("FingerTurnHard"),
        _finger_reward("FingerTurnHard"),
    ),
}
