"""Two DeepMind Control tasks on native MuJoCo: the ones MJX runs slowest on a CPU.

MuJoCo Playground's MJX ports of ball-in-cup and finger-turn are the contact-rich tasks
of the sparse suite. MuJoCo's C engine runs them faster on a CPU: in PPO with action
noise (64 envs x 64 steps, the first 61,440 steps of a run) 19.2k env steps/s against
11.9k on MJX for ball-in-cup, 25.3k against 17.3k for finger turn hard
(``python -m coherent_jax.bench physics env=dmc-ball_in_cup`` times the physics alone).
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

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from coherent_jax.envs.brax_env import make_playground_env
from coherent_jax.envs.mujoco_task import Kinematics, NativeModel, NativeTask


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
