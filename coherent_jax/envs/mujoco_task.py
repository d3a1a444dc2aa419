"""What a MuJoCo task is: the MjData fields it reads and its formulas (`NativeTask`).

A task's observation, reward and termination are pure JAX functions of a few MjData
fields after a reset or a step (`Kinematics`), so the same formulas run on any engine
that can produce those fields (`coherent_jax.envs.physics`): native MuJoCo through a
callback or MJX inside the program. The built-in MuJoCo tasks are written in this form
(`coherent_jax.envs.gym_v5`, `coherent_jax.envs.native_ports`), and a user's MJCF task is
turned into it (`coherent_jax.envs.user`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from coherent_jax.envs.action_map import ActionMap


class Kinematics(NamedTuple):
    """MjData fields of one env after a reset or a step, float32, laid out as MuJoCo lays them out
    (body 0 is the world). A task reads only the fields it names (`NativeTask.fields`); the others
    are None.

    After ``mj_step`` the position-dependent fields (``xpos``, ``cinert``, ...) describe
    the state before the last substep, because MuJoCo computes kinematics before it
    integrates; the tasks' formulas inherit that, as Brax and Gymnasium do.

    Attributes:
      qpos: [nq] joint positions.
      qvel: [nv] joint velocities.
      xpos: [nbody, 3] body frame positions.
      xquat: [nbody, 4] body orientations (w, x, y, z).
      xipos: [nbody, 3] body centres of mass.
      site_xpos: [nsite, 3] site positions.
      qfrc_constraint: [nv] constraint forces.
      qfrc_actuator: [nv] actuator forces.
      cinert: [nbody, 10] com-based body inertias.
      cvel: [nbody, 6] com-based body velocities.
      cfrc_ext: [nbody, 6] com-based external (contact) forces, as ``mj_rnePostConstraint``
        computes them after the step.
      sensordata: [nsensordata] the model's sensors, as the forward pass of the step left them.
    """

    qpos: jax.Array
    qvel: jax.Array
    xpos: Any = None
    xquat: Any = None
    xipos: Any = None
    site_xpos: Any = None
    qfrc_constraint: Any = None
    qfrc_actuator: Any = None
    cinert: Any = None
    cvel: Any = None
    cfrc_ext: Any = None
    sensordata: Any = None


# Fields that ``mj_step`` leaves stale and ``mj_rnePostConstraint`` computes.
POST_CONSTRAINT_FIELDS = frozenset({"cfrc_ext"})


class NativeModel(NamedTuple):
    """A task's compiled model and how an env step uses it.

    Attributes:
      model: the ``MjModel`` (shared: callers must not modify it).
      n_frames: ``mj_step`` calls per env step.
      dt: env step duration in seconds (``n_frames * opt.timestep``).
      init_q: [nq] float32 pose the reset noise is added to.
    """

    model: Any
    n_frames: int
    dt: float
    init_q: Any


@dataclasses.dataclass(frozen=True)
class NativeTask:
    """One task on native MuJoCo: its model, the fields it reads and its formulas.

    Attributes:
      load: () -> `NativeModel`, builds the model (called once per process).
      fields: the `Kinematics` fields the formulas read.
      reset_noise: (key, init_q, nv) -> (qpos, qvel), the initial-state distribution; or
        (qpos, qvel, mocap_pos [nmocap, 3]) for a task that also places mocap bodies, which
        are set after the reset's forward pass (as MuJoCo Playground sets its targets).
      observe: `Kinematics` -> obs.
      reward_done: (kin before, kin after, ctrl, dt) -> (reward, done); ``ctrl`` is the
        control applied (the action mapped to the actuators' range where `scale_action`).
      scale_action: map the action from [-1, 1] affinely onto the actuators' ctrlrange.
      brax_scaling: compute that map as Brax does, ``(a + 1) (high - low) / 2 + low``, rather
        than as ``centre + a * half-width`` (exactly ``a * high`` on a symmetric range, the
        action Gymnasium's env receives); the two round differently.
      normalize_quaternions: normalise free and ball joints' quaternions of a fresh
        state before its first forward pass (as MJX does to Brax's noisy poses; Gymnasium
        keeps them as drawn).
      source: where the task is defined, for messages ("Brax 0.14.2", "Gymnasium 1.4.0 v5").
    """

    load: Callable[[], NativeModel]
    fields: tuple[str, ...]
    reset_noise: Callable[..., tuple[jax.Array, jax.Array]]
    observe: Callable[[Kinematics], jax.Array]
    reward_done: Callable[..., tuple[jax.Array, jax.Array]]
    scale_action: bool = False
    brax_scaling: bool = False
    normalize_quaternions: bool = False
    source: str = ""


def control(task: NativeTask, action: jax.Array, ctrl_range) -> jax.Array:
    """The actuators' controls for ``action`` [..., nu] in [-1, 1]: as given, or mapped
    affinely onto ``ctrl_range`` [nu, 2] (the model's ``actuator_ctrlrange``) where the
    task scales actions, in Brax's or Gymnasium's arithmetic (`NativeTask.brax_scaling`),
    by the task's `coherent_jax.envs.action_map.ActionMap`."""
    return ActionMap.of_task(task.scale_action, task.brax_scaling, ctrl_range).unclipped(action)


def uniform_reset(q_scale: float, qd_scale: float, qd_normal: bool):
    """Reset noise q0 + U(-q_scale, q_scale); qd = qd_scale N(0, 1) or U(-qd_scale, qd_scale).

    Brax's tasks and Gymnasium's (whose initial velocities are zero) draw from this family.
    """

    def reset(key: jax.Array, init_q: jax.Array, nv: int) -> tuple[jax.Array, jax.Array]:
        _, k_q, k_qd = jax.random.split(key, 3)
        q = init_q + jax.random.uniform(k_q, init_q.shape, minval=-q_scale, maxval=q_scale)
        if qd_normal:
            qd = qd_scale * jax.random.normal(k_qd, (nv,))
        else:
            qd = jax.random.uniform(k_qd, (nv,), minval=-qd_scale, maxval=qd_scale)
        return q, qd

    return reset


def quat_rotate(quat: jax.Array, vec: jax.Array) -> jax.Array:
    """Rotates `vec` by the unit quaternion `quat` = (w, x, y, z)."""
    w, u = quat[0], quat[1:]
    return vec + 2.0 * jnp.cross(u, jnp.cross(u, vec) + w * vec)
