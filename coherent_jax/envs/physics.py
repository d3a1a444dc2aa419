"""The engines that run a MuJoCo task (`NativeTask`): native MuJoCo called from inside the
jitted step (`NativePhysics`), and MJX inside the program (`MjxPhysics`); what both share
(`TaskPhysics`); and the `NativeTask` of each task that has one (`NATIVE_TASKS`, `native_task`).
Which task runs on which engine is the registry's (`coherent_jax.envs.registry.resolve_physics`,
``physics=native`` or ``physics=mjx``).

**Native MuJoCo.** MJX runs MuJoCo's algorithms as XLA programs; on a CPU they are several
times slower than MuJoCo's own C engine (``docs/benchmarks.md``). `NativePhysics` steps
MuJoCo models with the C engine instead: all envs of a call at once, on a thread pool
(``mujoco.batch.Batch``), reached from JAX through ``jax.pure_callback``, so the training
iteration stays one jitted function. A task (`NativeTask`) names the MjData fields it reads
and gives its formulas in JAX; these run here:

* Gymnasium's MuJoCo v5 tasks (`coherent_jax.envs.gym_v5`), the standard ones, with
  Gymnasium's own MJCF, integrator and solver;
* six of Brax's re-creations (``brax-*``), the same task as their MJX version: the
  ``MjModel`` Brax builds, with the MJX task's solver options (``TaskSpec.ls_iterations``
  and Brax's own overrides, such as ant's Newton solver with one iteration) copied
  onto it, the same substeps, the same reset noise drawn from the same JAX keys, and
  the formulas of Brax's env classes (`coherent_jax.envs.native_ports`);
* two of MuJoCo Playground's DeepMind Control tasks (``dmc-ball_in_cup``,
  ``dmc-finger_turn_hard``; `coherent_jax.envs.native_ports`), the ones MJX runs slowest.
* the user's own tasks, ``env=MODULE:NAME`` (`coherent_jax.envs.user`).

The physics state lives in JAX, not in the engine: each env's float64
``mjSTATE_INTEGRATION`` row (positions, velocities, controls, solver warm start,
...) travels bit for bit as uint32 pairs, because JAX runs in float32. A call
loads the rows, steps and returns the new rows, so the callback is a pure function
of its inputs: runs are reproducible from the seed, and ``jax.vmap`` (a sweep over
seeds) just batches more rows into the same call.

**MJX** (``physics=mjx``): `MjxPhysics` steps the same MjModel with MJX (``mjx.put_model``:
Gymnasium's integrator, solver, iterations, contacts and timestep, as loaded), so the whole
env step is JAX and runs where JAX runs: the path for accelerators. Observation, reward and
termination are the task's own formulas, applied to the same `Kinematics` fields, read from
MJX's data instead of MjData's. MJX computes in float32 (native MuJoCo in float64), so
trajectories agree with Gymnasium's to float32 accuracy for a few steps and then drift apart
as any two float precisions do through contacts (``tests/test_gymnasium_tasks.py`` measures
how far). Humanoid-v5 solves its contacts with PGS, which MJX does not implement: refused
(`coherent_jax.envs.registry.MJX_REFUSAL`).
"""

from __future__ import annotations

import os
import threading
from typing import Any

import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import batch, mjx

from coherent_jax.envs.gym_v5 import GYM_TASKS
from coherent_jax.envs.mujoco_task import (
    POST_CONSTRAINT_FIELDS,
    Kinematics,
    NativeModel,
    NativeTask,
    control,
)
from coherent_jax.envs.native_ports import BRAX_NATIVE, DMC_NATIVE
from coherent_jax.envs.registry import DEFAULT_THREADS, SHORT_NAMES, is_user_task, resolve_physics
from coherent_jax.envs.user import load_user_task


@struct.dataclass
class PhysicsState:
    """Physics state of `n` envs of a `TaskPhysics` engine.

    Attributes:
      engine: the engine's own state of every env (`NativePhysics`: the MjData rows;
        `MjxPhysics`: a batched ``mjx.Data``).
      kin: `Kinematics` of every env, [n, ...].
      obs: [n, obs_size] observation.
      reward: [n] reward of the step that led here (0 after a reset).
      done: [n] 1.0 where the task's termination condition holds.
    """

    engine: Any
    kin: Kinematics
    obs: jax.Array
    reward: jax.Array
    done: jax.Array


class TaskPhysics:
    """What every engine of a `NativeTask` shares (`NativePhysics`, `MjxPhysics`): the reset
    distribution, the action map, and observation, reward and termination from the
    `Kinematics` an engine produces. Subclasses set ``spec``, ``init_q``, ``nq``, ``nv``,
    ``dt``, ``action_size``, ``ctrl_range`` and ``state_type``, and write how their engine
    places a fresh state (`_place`) and advances one env step (`_advance`)."""

    spec: NativeTask
    init_q: jax.Array
    nq: int
    nv: int
    dt: float
    action_size: int
    ctrl_range: Any
    state_type: type[PhysicsState] = PhysicsState

    def reset(self, keys: jax.Array) -> PhysicsState:
        """Initial states of len(keys) envs, one key each (the task's reset distribution)."""
        draws = jax.vmap(lambda k: self.spec.reset_noise(k, self.init_q, self.nv))(keys)
        return self.reset_to(*draws)

    def reset_to(self, qpos: jax.Array, qvel: jax.Array, mocap_pos: jax.Array | None = None) -> PhysicsState:
        """n envs at joint positions [n, nq] and velocities [n, nv] (and mocap bodies at
        ``mocap_pos`` [n, nmocap, 3], placed after the forward pass), as a reset leaves them."""
        n = qpos.shape[0]
        chex.assert_shape([qpos, qvel], [(n, self.nq), (n, self.nv)])
        engine, kin = self._place(qpos, qvel, mocap_pos)
        obs, reward, done = self._outputs(kin)
        return self.state_type(engine=engine, kin=kin, obs=obs, reward=reward, done=done)

    def step(self, state: PhysicsState, action: jax.Array) -> PhysicsState:
        """One env step (the task's substeps) of every env with `action` [n, action_size]."""
        chex.assert_shape(action, (state.obs.shape[0], self.action_size))
        ctrl = control(self.spec, action, self.ctrl_range)
        engine, kin = self._advance(state.engine, ctrl)
        obs, reward, done = self._outputs(kin, state.kin, ctrl)
        return self.state_type(engine=engine, kin=kin, obs=obs, reward=reward, done=done)

    def _place(self, qpos: jax.Array, qvel: jax.Array, mocap_pos: jax.Array | None):
        """(engine state, `Kinematics`) of fresh envs after the forward pass."""
        raise NotImplementedError

    def _advance(self, engine: Any, ctrl: jax.Array):
        """(engine state, `Kinematics`) after one env step with controls ``ctrl`` [n, nu]."""
        raise NotImplementedError

    def trajectory(self, keys: jax.Array, actions: jax.Array):
        """Resets len(keys) envs from ``keys``, then steps them with ``actions`` [T, n, nu]
        (a `lax.scan`; jit it). Returns (first obs [n, o], (obs [T, n, o], reward [T, n],
        done [T, n])): what comparisons of two engines or against Gymnasium read."""

        def body(state, action):
            state = self.step(state, action)
            return state, (state.obs, state.reward, state.done)

        state = self.reset(keys)
        return state.obs, jax.lax.scan(body, state, actions)[1]

    def _outputs(self, kin: Kinematics, before: Kinematics | None = None, ctrl: jax.Array | None = None):
        """(obs, reward, done) of every env [n, ...]: after a step from ``before`` with ``ctrl``,
        or after a reset (``before`` None: reward and done 0)."""
        obs = jax.vmap(self.spec.observe)(kin)
        if before is None:
            zeros = jnp.zeros(obs.shape[:1], jnp.float32)
            return obs, zeros, zeros
        reward, done = jax.vmap(lambda k0, k1, c: self.spec.reward_done(k0, k1, c, self.dt))(
            before, kin, ctrl
        )
        return obs, reward.astype(jnp.float32), done.astype(jnp.float32)


# --- native MuJoCo
@struct.dataclass
class NativeState(PhysicsState):
    """`PhysicsState` of envs stepped by native MuJoCo: ``engine`` is [n, 2 * nstate] uint32,
    the float64 ``mjSTATE_INTEGRATION`` rows bit for bit."""


# Every task native MuJoCo runs, by registry name (the names are `registry.NATIVE_TASKS`,
# which the config reads without JAX): Gymnasium's (by id and by short name), six of Brax's and two of the
# DeepMind Control Suite's.
NATIVE_TASKS: dict[str, NativeTask] = {
    **{short: GYM_TASKS[gym_id] for short, gym_id in SHORT_NAMES.items()},
    **GYM_TASKS,
    **BRAX_NATIVE,
    **DMC_NATIVE,
}


def native_task(task: str) -> NativeTask:
    """The `NativeTask` of registry name `task`, or of a user's ``MODULE:NAME`` (imported and
    checked by `coherent_jax.envs.user`); raises naming the supported tasks otherwise."""
    if is_user_task(task):
        return load_user_task(task).native
    if task not in NATIVE_TASKS:
        resolve_physics(task, "native")  # raises naming the supported tasks
    return NATIVE_TASKS[task]


def mujoco_model(task: str) -> NativeModel:
    """(``MjModel``, n_frames, dt, init_q) of native task `task`; cached, callers must not modify it."""
    return native_task(task).load()


class _Host:
    """The host side: one MuJoCo model and a `mujoco.batch.Batch` per batch size.

    Returns, after a reset or a step, the state rows and the task's `Kinematics` fields
    as float32 arrays. ``cfrc_ext`` needs ``mj_rnePostConstraint`` after the step (as
    Gymnasium calls it), which a batch call does not run: tasks that read it keep a
    persistent batch (one ``MjData`` per env) and run it per env on the host.
    """

    def __init__(self, model, n_frames: int, nthread: int, fields: tuple[str, ...], normalize: bool):
        self.model = model
        self.n_frames = n_frames
        self.nthread = nthread
        self.fields = fields
        self.post_constraint = tuple(f for f in fields if f in POST_CONSTRAINT_FIELDS)
        self.nstate = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION)
        self._batches: dict[int, Any] = {}
        self._lock = threading.Lock()
        self._data = mujoco.MjData(model) if self.post_constraint else None
        # qpos addresses of the free and ball joints' quaternions.
        free, ball = int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL)
        self._quats = (
            [
                int(adr) + (3 if jtype == free else 0)
                for jtype, adr in zip(model.jnt_type, model.jnt_qposadr, strict=True)
                if jtype in (free, ball)
            ]
            if normalize
            else []
        )

    def shapes(self) -> dict[str, tuple[int, ...]]:
        """Per-env shape of each field the host returns."""
        data = mujoco.MjData(self.model)
        return {name: tuple(getattr(data, name).shape) for name in self.fields}

    def _batch(self, n: int):
        if n not in self._batches:
            b = batch.Batch(
                self.model, n, nthread=min(self.nthread, n), persistent=bool(self.post_constraint)
            )
            # Derived fields are copied out only once bound: bind them before any call.
            for name in self.fields:
                if name not in self.post_constraint:
                    b.bind(name)
            self._batches[n] = b
        return self._batches[n]

    def _read(self, b, after_step: bool) -> tuple[np.ndarray, ...]:
        n = b.nsim
        rows = np.ascontiguousarray(b.state).view(np.uint32).reshape(n, 2 * self.nstate)
        post = {}
        if self.post_constraint:
            post = {
                name: np.zeros((n, *getattr(self._data, name).shape), np.float32)
                for name in self.post_constraint
            }
            if after_step:  # mj_forward leaves them zero after a reset, as in Gymnasium
                for i in range(n):
                    b.get_data(i, self._data)
                    mujoco.mj_rnePostConstraint(self.model, self._data)
                    for name in self.post_constraint:
                        post[name][i] = getattr(self._data, name)
        return (rows.copy(), *(post[f] if f in post else b.bind(f).astype(np.float32) for f in self.fields))

    def reset(
        self, qpos: np.ndarray, qvel: np.ndarray, mocap_pos: np.ndarray | None = None
    ) -> tuple[np.ndarray, ...]:
        """Fresh states at (qpos, qvel), zero controls and warm start, then mj_forward.

        Brax's tasks normalise quaternions first, as MJX's forward pass does to Brax's
        noisy initial poses (MuJoCo's C forward pass only normalises a copy). ``mocap_pos``
        [..., nmocap, 3] is written into the state after the forward pass and the fields
        are read, so they describe the model's default mocap bodies until the first step
        (MuJoCo Playground's order).
        """
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
            out = self._read(b, after_step=False)
            if mocap_pos is not None:
                b.bind("mocap_pos")[:] = np.asarray(mocap_pos, np.float64).reshape(qpos.shape[0], -1, 3)
                rows = np.ascontiguousarray(b.state).view(np.uint32).reshape(qpos.shape[0], -1)
                out = (rows.copy(), *out[1:])
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
            out = self._read(b, after_step=True)
        return tuple(o.reshape(lead + o.shape[1:]) for o in out)


class NativePhysics(TaskPhysics):
    """Batched reset and step of one task on native MuJoCo, callable under jit.

    Unlike a Brax env (one env, vmapped by the caller) both methods take the
    whole batch: the callback hands all envs to MuJoCo's thread pool at once.
    """

    state_type = NativeState

    def __init__(self, task: str, nthread: int = DEFAULT_THREADS):
        self.spec = native_task(task)  # raises for a task it cannot run
        model, self.n_frames, self.dt, init_q = self.spec.load()
        self.task = task
        self.host = _Host(
            model,
            self.n_frames,
            int(nthread) or os.cpu_count() or 1,
            self.spec.fields,
            self.spec.normalize_quaternions,
        )
        self.nq, self.nv = model.nq, model.nv
        self.action_size = int(model.nu)
        self.init_q = jnp.asarray(init_q)
        self.ctrl_range = np.asarray(model.actuator_ctrlrange, np.float32)
        self._field_shapes = self.host.shapes()
        kin = Kinematics(**{f: jnp.zeros(s) for f, s in self._field_shapes.items()})
        self.observation_size = int(jax.eval_shape(self.spec.observe, kin).shape[-1])

    def _shapes(self, n: int):
        return (
            jax.ShapeDtypeStruct((n, 2 * self.host.nstate), jnp.uint32),
            *(jax.ShapeDtypeStruct((n, *s), jnp.float32) for s in self._field_shapes.values()),
        )

    def _kinematics(self, arrays) -> Kinematics:
        return Kinematics(**dict(zip(self._field_shapes, arrays, strict=True)))

    def _place(self, qpos: jax.Array, qvel: jax.Array, mocap_pos: jax.Array | None):
        args = (qpos, qvel) if mocap_pos is None else (qpos, qvel, mocap_pos)
        shapes = self._shapes(qpos.shape[0])
        rows, *arrays = jax.pure_callback(self.host.reset, shapes, *args, vmap_method="broadcast_all")
        return rows, self._kinematics(arrays)

    def _advance(self, rows: jax.Array, ctrl: jax.Array):
        shapes = self._shapes(rows.shape[0])
        rows, *arrays = jax.pure_callback(self.host.step, shapes, rows, ctrl, vmap_method="broadcast_all")
        return rows, self._kinematics(arrays)


# --- MJX
@struct.dataclass
class MjxState(PhysicsState):
    """`PhysicsState` of envs stepped by MJX: ``engine`` is a batched ``mjx.Data`` (leading axis n)."""


class MjxPhysics(TaskPhysics):
    """Batched reset and step of one native task's model on MJX; pure and jit-able.

    The same interface as `NativePhysics` (whole batches in,
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
