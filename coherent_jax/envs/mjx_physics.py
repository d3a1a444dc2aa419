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

import jax
import jax.numpy as jnp
from flax import struct
from mujoco import mjx

from coherent_jax.envs.task import (
    POST_CONSTRAINT_FIELDS,
    Kinematics,
    NativeModel,
    NativeTask,
    PhysicsState,
    TaskPhysics,
)


@struct.dataclass
class MjxState(PhysicsState):
    """`PhysicsState` of envs stepped by MJX: ``engine`` is a batched ``mjx.Data`` (leading axis n)."""


class MjxPhysics(TaskPhysics):
    """Batched reset and step of one native task's model on MJX; pure and jit-able.

    The same interface as `coherent_jax.envs.native.NativePhysics` (whole batches in,
    whole batches out), so `VecEnv` uses either in the same way.
    """

    state_type = MjxState

    def __init__(self, task: str, spec: NativeTask, native_model: NativeModel):
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
        qpos = qpos.astype(self._blank.qpos.dtype)
        data = mjx.forward(
            self.model, self._blank.replace(qpos=qpos, qvel=qvel.astype(self._blank.qvel.dtype))
        )
        # MJX's forward pass writes free joints' quaternions back normalised; MuJoCo's C
        # pass normalises a copy, so Gymnasium (and native) observe the pose as drawn.
        # cfrc_ext stays zero, as mj_forward leaves it.
        return data.replace(qpos=qpos)

    def _step_one(self, data, ctrl: jax.Array):
        data = data.replace(ctrl=ctrl.astype(data.ctrl.dtype))
        data = jax.lax.fori_loop(0, self.n_frames, lambda _, d: mjx.step(self.model, d), data)
        return mjx.rne_postconstraint(self.model, data) if self._post else data

    def _place(self, qpos: jax.Array, qvel: jax.Array, mocap_pos: jax.Array | None):
        if mocap_pos is not None:  # no task run here places mocap bodies
            raise NotImplementedError("MjxPhysics does not place mocap bodies")
        data = jax.vmap(self._reset_one)(qpos, qvel)
        return data, jax.vmap(self._kinematics)(data)

    def _advance(self, data, ctrl: jax.Array):
        data = jax.vmap(self._step_one)(data, ctrl)
        return data, jax.vmap(self._kinematics)(data)
