"""Native MuJoCo physics for the MJX tasks, called from inside the jitted step.

MJX runs MuJoCo's algorithms as XLA programs; on a CPU they are several times
slower than MuJoCo's own C engine (``DESIGN.md`` §5). This module steps the same
models with the C engine instead: all envs of a call at once, on a thread pool
(``mujoco.batch.Batch``), reached from JAX through ``jax.pure_callback``, so the
training iteration stays one jitted function.

What makes it the same task as the MJX one:

* the same ``MjModel``: the one Brax builds from its MJCF, with the solver options
  of the MJX task (``TaskSpec.ls_iterations`` and Brax's own overrides, such as
  ant's Newton solver with one iteration) copied onto it;
* the same ``n_frames`` substeps per env step, the same reset-noise distributions
  drawn from the same JAX keys, and the observation, reward and termination
  formulas of Brax's env classes, written below per task. Body positions are read
  as Brax reads them from MJX: after ``mj_step`` they describe the state before the
  last substep (MuJoCo computes kinematics before it integrates), which the reward
  of the running tasks inherits.

The physics state lives in JAX, not in the engine: each env's float64
``mjSTATE_INTEGRATION`` row (positions, velocities, controls, solver warm start,
...) travels bit for bit as uint32 pairs, because JAX runs in float32. A call
loads the rows, steps and returns the new rows, so the callback is a pure function
of its inputs: runs are reproducible from the seed, and ``jax.vmap`` (a sweep over
seeds) just batches more rows into the same call.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import threading
from collections.abc import Callable
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from coherent_jax.envs.registry import check_task, make_brax_env

PHYSICS = ("auto", "mjx", "native")
# MuJoCo threads per call (0 = every core). On the shared 2-core machine one thread
# was as fast as two or faster in 2 of 3 runs of `python -m coherent_jax.bench_physics`
# (loaded machine: 25k vs 15k env steps/s at 64 halfcheetah envs); on a quiet moment
# two threads gave 41k vs 21k at 64 envs. A dedicated machine should try 0.
DEFAULT_THREADS = 1


class Kinematics(NamedTuple):
    """What the task formulas read from one env after a reset or a step (float32).

    Attributes:
      qpos: [nq] joint positions (Brax's ``q``).
      qvel: [nv] joint velocities (Brax's ``qd``).
      xpos: [nbody - 1, 3] body positions without the world body (Brax's ``x.pos``).
      xquat: [nbody - 1, 4] body orientations (Brax's ``x.rot``).
    """

    qpos: jax.Array
    qvel: jax.Array
    xpos: jax.Array
    xquat: jax.Array


@struct.dataclass
class NativeState:
    """Physics state of `n` envs stepped by native MuJoCo.

    Attributes:
      integration: [n, 2 * nstate] uint32, the float64 ``mjSTATE_INTEGRATION`` rows bit for bit.
      kin: `Kinematics` of every env, [n, ...].
      obs: [n, obs_size] observation.
      reward: [n] reward of the step that led here (0 after a reset).
      done: [n] 1.0 where the task's termination condition holds.
    """

    integration: jax.Array
    kin: Kinematics
    obs: jax.Array
    reward: jax.Array
    done: jax.Array


def _uniform_reset(q_scale: float, qd_scale: float, qd_normal: bool):
    """Brax's reset noise: q0 + U(-q_scale, q_scale); qd = qd_scale N(0, 1) or U(-qd_scale, qd_scale)."""

    def reset(key: jax.Array, init_q: jax.Array, nv: int) -> tuple[jax.Array, jax.Array]:
        _, k_q, k_qd = jax.random.split(key, 3)
        q = init_q + jax.random.uniform(k_q, init_q.shape, minval=-q_scale, maxval=q_scale)
        if qd_normal:
            qd = qd_scale * jax.random.normal(k_qd, (nv,))
        else:
            qd = jax.random.uniform(k_qd, (nv,), minval=-qd_scale, maxval=qd_scale)
        return q, qd

    return reset


def _quat_rotate(quat: jax.Array, vec: jax.Array) -> jax.Array:
    """Rotates `vec` by the unit quaternion `quat` = (w, x, y, z)."""
    w, u = quat[0], quat[1:]
    return vec + 2.0 * jnp.cross(u, jnp.cross(u, vec) + w * vec)


# --- per-task formulas (Brax 0.14.2, brax/envs/<task>.py; `dt` is the env step).
def _halfcheetah_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate([k.qpos[1:], k.qvel])


def _halfcheetah_reward(k0: Kinematics, k1: Kinematics, action: jax.Array, dt: float):
    """r = (x_torso' - x_torso) / dt - 0.1 |a|^2; never terminates."""
    reward = (k1.xpos[0, 0] - k0.xpos[0, 0]) / dt - 0.1 * jnp.sum(jnp.square(action))
    return reward, jnp.zeros(())


def _inverted_pendulum_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate([k.qpos, k.qvel])


def _inverted_pendulum_reward(k0: Kinematics, k1: Kinematics, action: jax.Array, dt: float):
    """r = 1; done when the pole angle |q_1| > 0.2."""
    return jnp.ones(()), (jnp.abs(k1.qpos[1]) > 0.2).astype(jnp.float32)


def _planar_obs(k: Kinematics) -> jax.Array:
    """Hopper and walker2d: q with q_1 replaced by the torso height, x dropped; qd clipped to [-10, 10]."""
    position = k.qpos.at[1].set(k.xpos[0, 2])[1:]
    return jnp.concatenate([position, jnp.clip(k.qvel, -10.0, 10.0)])


def _hopper_reward(k0: Kinematics, k1: Kinematics, action: jax.Array, dt: float):
    """r = vx + 1 - 1e-3 |a|^2; healthy: |(q_2:, qd)| < 100, z > 0.7, |angle| < 0.2."""
    z, angle = k1.xpos[0, 2], k1.qpos[2]
    state_vec = jnp.concatenate([k1.qpos[2:], k1.qvel])
    healthy = jnp.all((state_vec > -100.0) & (state_vec < 100.0)) & (z > 0.7) & (angle > -0.2) & (angle < 0.2)
    reward = (k1.xpos[0, 0] - k0.xpos[0, 0]) / dt + 1.0 - 1e-3 * jnp.sum(jnp.square(action))
    return reward, 1.0 - healthy.astype(jnp.float32)


def _walker2d_reward(k0: Kinematics, k1: Kinematics, action: jax.Array, dt: float):
    """r = vx + 1 - 1e-3 |a|^2; healthy: 0.8 < z < 2, -1 < angle < 1."""
    z, angle = k1.xpos[0, 2], k1.qpos[2]
    healthy = (z > 0.8) & (z < 2.0) & (angle > -1.0) & (angle < 1.0)
    reward = (k1.xpos[0, 0] - k0.xpos[0, 0]) / dt + 1.0 - 1e-3 * jnp.sum(jnp.square(action))
    return reward, 1.0 - healthy.astype(jnp.float32)


def _ant_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate([k.qpos[2:], k.qvel])


def _ant_reward(k0: Kinematics, k1: Kinematics, action: jax.Array, dt: float):
    """r = vx + 1 - 0.5 |a|^2 (no contact cost); healthy: 0.2 <= z_torso <= 1."""
    z = k1.xpos[0, 2]
    healthy = (z >= 0.2) & (z <= 1.0)
    reward = (k1.xpos[0, 0] - k0.xpos[0, 0]) / dt + 1.0 - 0.5 * jnp.sum(jnp.square(action))
    return reward, 1.0 - healthy.astype(jnp.float32)


def _double_pendulum_obs(k: Kinematics) -> jax.Array:
    return jnp.concatenate(
        [k.qpos[:1], jnp.sin(k.qpos[1:]), jnp.cos(k.qpos[1:]), jnp.clip(k.qvel, -10.0, 10.0)]
    )


def _double_pendulum_reward(k0: Kinematics, k1: Kinematics, action: jax.Array, dt: float):
    """Tip = pole2 frame applied to (0, 0, 0.6); done when tip y <= 1;
    r = 10 (1 - done) - 0.01 x^2 - (y - 2)^2 - 1e-3 v1^2 - 5e-3 v2^2."""
    tip = k1.xpos[2] + _quat_rotate(k1.xquat[2], jnp.array([0.0, 0.0, 0.6]))
    x, y = tip[0], tip[2]
    v1, v2 = k1.qvel[1], k1.qvel[2]
    done = (y <= 1.0).astype(jnp.float32)
    reward = (1.0 - done) * 10.0 - (0.01 * x**2 + (y - 2.0) ** 2) - (1e-3 * v1**2 + 5e-3 * v2**2)
    return reward, done


@dataclasses.dataclass(frozen=True)
class NativeTask:
    """Observation, reward and termination of one task, as Brax's env class computes them.

    Attributes:
      reset_noise: (key, init_q, nv) -> (q, qd), the initial-state distribution.
      observe: `Kinematics` -> obs.
      reward_done: (kin before, kin after, action, dt) -> (reward, done).
      scale_action: map the action from [-1, 1] to the actuators' ctrlrange (Brax's
        inverted_pendulum does; the others pass it through).
    """

    reset_noise: Callable[..., tuple[jax.Array, jax.Array]]
    observe: Callable[[Kinematics], jax.Array]
    reward_done: Callable[..., tuple[jax.Array, jax.Array]]
    scale_action: bool = False


NATIVE_TASKS: dict[str, NativeTask] = {
    "halfcheetah": NativeTask(_uniform_reset(0.1, 0.1, True), _halfcheetah_obs, _halfcheetah_reward),
    "inverted_pendulum": NativeTask(
        _uniform_reset(0.01, 0.01, False), _inverted_pendulum_obs, _inverted_pendulum_reward, True
    ),
    "hopper": NativeTask(_uniform_reset(5e-3, 5e-3, False), _planar_obs, _hopper_reward),
    "walker2d": NativeTask(_uniform_reset(5e-3, 5e-3, False), _planar_obs, _walker2d_reward),
    "ant": NativeTask(_uniform_reset(0.1, 0.1, True), _ant_obs, _ant_reward),
    "inverted_double_pendulum": NativeTask(
        _uniform_reset(0.01, 0.01, True), _double_pendulum_obs, _double_pendulum_reward
    ),
}


class PhysicsError(ValueError):
    """A physics backend that does not exist or does not support the task."""


def resolve_physics(task: str, physics: str) -> str:
    """The backend a task runs on: ``mjx`` or ``native`` (own-pipeline tasks keep theirs).

    ``auto`` picks native MuJoCo on a CPU for the tasks that have it (several times
    faster there, see ``python -m coherent_jax.bench_physics``) and MJX on
    accelerators. Raises `PhysicsError` with a one-line message otherwise.
    """
    spec = check_task(task)
    if physics not in PHYSICS:
        raise PhysicsError(f"unknown physics {physics!r}; valid: {', '.join(PHYSICS)}")
    if physics == "native" and task not in NATIVE_TASKS:
        raise PhysicsError(
            f"physics=native does not support env {task!r}; supported envs: {', '.join(NATIVE_TASKS)}"
        )
    if spec.backend != "mjx":
        return spec.backend
    if physics == "auto":
        return "native" if task in NATIVE_TASKS and jax.default_backend() == "cpu" else "mjx"
    return physics


@functools.cache
def mujoco_model(task: str):
    """(``MjModel``, n_frames, dt, init_q) of the MJX task `task`, with the solver options it uses.

    Cached (building the Brax env takes seconds): callers share the model and must not modify it.

    Brax builds its ``System`` from an ``MjModel`` and then replaces options on the
    ``System`` only (``TaskSpec.ls_iterations``, ant's Newton solver, ...): copy them back.
    """
    import copy

    env = make_brax_env(task)
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
    return model, int(env._n_frames), float(env.dt), np.asarray(env.sys.init_q, np.float32)


class _Host:
    """The host side: one MuJoCo model and a `mujoco.batch.Batch` per batch size."""

    def __init__(self, model, n_frames: int, nthread: int):
        import mujoco

        self.model = model
        self.n_frames = n_frames
        self.nthread = nthread
        self.nstate = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION)
        self._batches: dict[int, Any] = {}
        self._lock = threading.Lock()
        # qpos addresses of the free and ball joints' quaternions.
        free, ball = int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL)
        self._quats = [
            int(adr) + (3 if jtype == free else 0)
            for jtype, adr in zip(model.jnt_type, model.jnt_qposadr, strict=True)
            if jtype in (free, ball)
        ]

    def _batch(self, n: int):
        from mujoco import batch

        if n not in self._batches:
            b = batch.Batch(self.model, n, nthread=min(self.nthread, n))
            # Derived fields are copied out only once bound: bind them before any call.
            for name in ("xpos", "xquat"):
                b.bind(name)
            self._batches[n] = b
        return self._batches[n]

    def _read(self, b) -> tuple[np.ndarray, ...]:
        n = b.nsim
        rows = np.ascontiguousarray(b.state).view(np.uint32).reshape(n, 2 * self.nstate)
        return (
            rows.copy(),
            b.bind("qpos").astype(np.float32),
            b.bind("qvel").astype(np.float32),
            b.bind("xpos")[:, 1:].astype(np.float32),
            b.bind("xquat")[:, 1:].astype(np.float32),
        )

    def reset(self, qpos: np.ndarray, qvel: np.ndarray) -> tuple[np.ndarray, ...]:
        """Fresh states at (qpos, qvel), zero controls and warm start, then mj_forward.

        Quaternions are normalised first, as MJX's forward pass does to Brax's noisy
        initial poses (MuJoCo's C forward pass only normalises a copy).
        """
        import mujoco

        qpos, qvel = np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)  # callbacks get jax.Arrays
        lead = qpos.shape[:-1]
        qpos = qpos.reshape(-1, qpos.shape[-1])
        for adr in self._quats:
            quat = qpos[:, adr : adr + 4]
            qpos[:, adr : adr + 4] = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
        with self._lock:
            b = self._batch(qpos.shape[0])
            b.reset(stage=mujoco.mjtStage.mjSTAGE_NONE)
            b.bind("qpos")[:] = qpos
            b.bind("qvel")[:] = qvel.reshape(qpos.shape[0], -1)
            b.forward()
            out = self._read(b)
        return tuple(o.reshape(lead + o.shape[1:]) for o in out)

    def step(self, rows: np.ndarray, ctrl: np.ndarray) -> tuple[np.ndarray, ...]:
        """Loads the state rows, applies `ctrl` for `n_frames` calls of mj_step."""
        rows, ctrl = np.asarray(rows), np.asarray(ctrl)  # callbacks get jax.Arrays
        lead = rows.shape[:-1]
        rows = np.ascontiguousarray(rows.reshape(-1, rows.shape[-1]))
        with self._lock:
            b = self._batch(rows.shape[0])
            b.state[:] = rows.view(np.float64)
            b.bind("ctrl")[:] = ctrl.reshape(rows.shape[0], -1)
            b.step(nstep=self.n_frames)
            out = self._read(b)
        return tuple(o.reshape(lead + o.shape[1:]) for o in out)


class NativePhysics:
    """Batched reset and step of one task on native MuJoCo, callable under jit.

    Unlike a Brax env (one env, vmapped by the caller) both methods take the
    whole batch: the callback hands all envs to MuJoCo's thread pool at once.
    """

    def __init__(self, task: str, nthread: int = DEFAULT_THREADS):
        if task not in NATIVE_TASKS:
            resolve_physics(task, "native")  # raises naming the supported tasks
        self.task = task
        self.spec = NATIVE_TASKS[task]
        model, self.n_frames, self.dt, init_q = mujoco_model(task)
        self.host = _Host(model, self.n_frames, int(nthread) or os.cpu_count() or 1)
        self.nq, self.nv, self.nbody = model.nq, model.nv, model.nbody
        self.action_size = int(model.nu)
        self.init_q = jnp.asarray(init_q)
        self.ctrl_range = np.asarray(model.actuator_ctrlrange, np.float32)
        kin = Kinematics(
            jnp.zeros(self.nq),
            jnp.zeros(self.nv),
            jnp.zeros((self.nbody - 1, 3)),
            jnp.zeros((self.nbody - 1, 4)),
        )
        self.observation_size = int(jax.eval_shape(self.spec.observe, kin).shape[-1])

    def _shapes(self, n: int):
        f32 = jnp.float32
        return (
            jax.ShapeDtypeStruct((n, 2 * self.host.nstate), jnp.uint32),
            jax.ShapeDtypeStruct((n, self.nq), f32),
            jax.ShapeDtypeStruct((n, self.nv), f32),
            jax.ShapeDtypeStruct((n, self.nbody - 1, 3), f32),
            jax.ShapeDtypeStruct((n, self.nbody - 1, 4), f32),
        )

    def reset(self, keys: jax.Array) -> NativeState:
        """Initial states of len(keys) envs, one key each (Brax's reset distribution)."""
        n = keys.shape[0]
        qpos, qvel = jax.vmap(lambda k: self.spec.reset_noise(k, self.init_q, self.nv))(keys)
        rows, *kin = jax.pure_callback(
            self.host.reset, self._shapes(n), qpos, qvel, vmap_method="broadcast_all"
        )
        kin = Kinematics(*kin)
        return NativeState(
            integration=rows,
            kin=kin,
            obs=jax.vmap(self.spec.observe)(kin),
            reward=jnp.zeros((n,), jnp.float32),
            done=jnp.zeros((n,), jnp.float32),
        )

    def step(self, state: NativeState, action: jax.Array) -> NativeState:
        """One env step (`n_frames` MuJoCo steps) of every env with `action` [n, action_size]."""
        n = state.integration.shape[0]
        chex.assert_shape(action, (n, self.action_size))
        ctrl = action
        if self.spec.scale_action:
            low, high = self.ctrl_range[:, 0], self.ctrl_range[:, 1]
            ctrl = (action + 1.0) * (high - low) * 0.5 + low
        rows, *kin = jax.pure_callback(
            self.host.step,
            self._shapes(n),
            state.integration,
            ctrl.astype(jnp.float32),
            vmap_method="broadcast_all",
        )
        kin = Kinematics(*kin)
        reward, done = jax.vmap(lambda k0, k1, a: self.spec.reward_done(k0, k1, a, self.dt))(
            state.kin, kin, action
        )
        return NativeState(
            integration=rows,
            kin=kin,
            obs=jax.vmap(self.spec.observe)(kin),
            reward=reward.astype(jnp.float32),
            done=done.astype(jnp.float32),
        )
