"""Gymnasium's tasks on MJX (``physics=mjx``): the same model and formulas inside the program.

`NativePhysics` steps a task's MjModel with MuJoCo's C engine through a callback;
`MjxPhysics` steps the same MjModel with MJX (``mjx.put_model``: Gymnasium's
integrator, solver, iterations, contacts and timestep, as loaded), so the whole env
step is JAX and runs where JAX runs: the path for accelerators. Observation, reward
and termination are the task's own formulas (`coherent_jax.envs.task.NativeTask`),
applied to the same `Kinematics` fields, read from MJX's data instead of MjData's.

MJX computes in float32 (native MuJoCo in float64), so trajectories agree with
Gymnasium's to float32 accuracy for a few steps and then drift apart as any two float
precisions do through contacts (``tests/test_gymnasium_tasks.py`` measures how far).
Humanoid-v5 solves its contacts with PGS, which MJX does not implement: refused
(`coherent_jax.envs.registry.MJX_REFUSAL`).
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
from flax import struct

from coherent_jax.envs.task import (
    POST_CONSTRAINT_FIELDS,
    Kinematics,
    NativeModel,
    NativeTask,
    TaskPhysics,
    control,
)


@struct.dataclass
class MjxState:
    """Physics state of `n` envs stepped by MJX.

    Attributes:
      data: batched ``mjx.Data`` (leading axis n).
      kin: `Kinematics` of every env, [n, ...].
      obs: [n, obs_size] observation.
      reward: [n] reward of the step that led here (0 after a reset).
      done: [n] 1.0 where the task's termination condition holds.
    """

    data: object
    kin: Kinematics
    obs: jax.Array
    reward: jax.Array
    done: jax.Array


class MjxPhysics(TaskPhysics):
    """Batched reset and step of one native task's model on MJX; pure and jit-able.

    The same interface as `coherent_jax.envs.native.NativePhysics` (whole batches in,
    whole batches out), so `VecEnv` uses either in the same way.
    """

    def __init__(self, task: str, spec: NativeTask, native_model: NativeModel):
        from mujoco import mjx

        model, self.n_frames, self.dt, init_q = native_model
        self.task, self.spec = task, spec
        self.model = mjx.put_model(model)
        self.nq, self.nv = model.nq, model.nv
        self.action_size = int(model.nu)
        self.init_q = jnp.asarray(init_q)
        self.ctrl_range = jnp.asarray(model.actuator_ctrlrange, jnp.float32)
        self._blank = mjx.make_data(self.model)
        self._post = any(f in POST_CONSTRAINT_FIELDS for f in spec.fields)
        kin = jax.eval_shape(self._kinematics, self._blank)
        self.observation_size = int(jax.eval_shape(spec.observe, kin).shape[-1])

    def _kinematics(self, data) -> Kinematics:
        return Kinematics(**{f: getattr(data, f).astype(jnp.float32) for f in self.spec.fields})

    def _reset_one(self, qpos: jax.Array, qvel: jax.Array):
        from mujoco import mjx

        qpos = qpos.astype(self._blank.qpos.dtype)
        data = mjx.forward(
            self.model, self._blank.replace(qpos=qpos, qvel=qvel.astype(self._blank.qvel.dtype))
        )
        # MJX's forward pass writes free joints' quaternions back normalised; MuJoCo's C
        # pass normalises a copy, so Gymnasium (and native) observe the pose as drawn.
        # cfrc_ext stays zero, as mj_forward leaves it.
        return data.replace(qpos=qpos)

    def _step_one(self, data, ctrl: jax.Array):
        from mujoco import mjx

        data = data.replace(ctrl=ctrl.astype(data.ctrl.dtype))
        data = jax.lax.fori_loop(0, self.n_frames, lambda _, d: mjx.step(self.model, d), data)
        return mjx.rne_postconstraint(self.model, data) if self._post else data

    def reset_to(self, qpos: jax.Array, qvel: jax.Array, mocap_pos: jax.Array | None = None) -> MjxState:
        """n envs at joint positions [n, nq] and velocities [n, nv], as a reset leaves them."""
        if mocap_pos is not None:  # no task run here places mocap bodies
            raise NotImplementedError("MjxPhysics does not place mocap bodies")
        n = qpos.shape[0]
        chex.assert_shape([qpos, qvel], [(n, self.nq), (n, self.nv)])
        data = jax.vmap(self._reset_one)(qpos, qvel)
        kin = jax.vmap(self._kinematics)(data)
        obs, reward, done = self._outputs(kin)
        return MjxState(data=data, kin=kin, obs=obs, reward=reward, done=done)

    def step(self, state: MjxState, action: jax.Array) -> MjxState:
        """One env step (`n_frames` MJX steps) of every env with `action` [n, action_size]."""
        n = state.obs.shape[0]
        chex.assert_shape(action, (n, self.action_size))
        ctrl = control(self.spec, action, self.ctrl_range)
        data = jax.vmap(self._step_one)(state.data, ctrl)
        kin = jax.vmap(self._kinematics)(data)
        obs, reward, done = self._outputs(kin, state.kin, ctrl)
        return MjxState(data=data, kin=kin, obs=obs, reward=reward, done=done)
