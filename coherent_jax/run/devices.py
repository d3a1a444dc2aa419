"""Where a train state lives: spread over JAX devices (`jax.sharding`, data parallel, SPMD),
gathered from them to the host, and as a checkpoint's bytes.

A training run shards its environments: every array of the per-env part of the
train state (``env_state`` and the exploration ``carry``, leading axis
``num_envs``) is split over a 1-D device mesh along that axis, and everything
else (parameters, optimiser state, observation statistics, hyperparameters,
keys) is replicated. The iteration is jitted with these shardings as its input
and output shardings; XLA's SPMD partitioner then runs each device's envs on
that device and inserts the all-reduces that the batch means of the loss need,
so the gradient every device applies is the mean over *all* envs, the same
function as on one device (up to the order of float sums).

A sweep instead shards its leading grid-point axis: each device runs whole
points, with no communication at all.

Several hosts: with ``distributed=true`` the CLIs call `initialize`
(`jax.distributed.initialize()`) first (coordinator, process count and id from the
usual ``JAX_COORDINATOR_ADDRESS``-style environment or the cluster's own, e.g.
SLURM), after which `jax.devices()` lists every host's devices and the same mesh
spans them; only process 0 writes files.

A state on the host: `to_host` gathers a state spread over several processes (a
collective), `place` puts a host copy back as the same global arrays, and
`state_to_bytes` / `restore_state` are a checkpoint's ``state`` entry (the rest of the
record is `coherent_jax.run.checkpoint`'s, which reads without JAX). Decisions that
change which collectives run next (stop now, write a checkpoint) are agreed on by every
process (`largest`, `from_writer`). The part of several processes that runs before JAX
(the supervisor) is `coherent_jax.run.multihost`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import serialization
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from coherent_jax.agents.trainer import Trainer
from coherent_jax.config import ConfigError
from coherent_jax.envs.registry import check_task
from coherent_jax.run.checkpoint import CheckpointError
from coherent_jax.run.multihost import (
    DEFAULT_HEARTBEAT_TIMEOUT_S,
    DEFAULT_INIT_TIMEOUT_S,
    HEARTBEAT_TIMEOUT_ENV,
    INIT_TIMEOUT_ENV,
    _timeout,
)
from coherent_jax.sweep_axis import POINT_AXIS, vmap_points

ENV_AXIS = "envs"
# Fields of a train state whose arrays carry one row per env (leading axis num_envs).
PER_ENV_FIELDS = ("env_state", "carry", "reward_norm")


def resolve_num_devices(requested: int, env: str | None = None) -> int:
    """``requested`` devices (0 = all; for a Gymnasium `env`, whose copies step in one host pool,
    0 = one: `check_host_pool`); raises `ConfigError` if there are fewer."""
    available = jax.device_count()
    if requested == 0:
        return 1 if env is not None and check_task(env).backend == "gym" else available
    if requested > available:
        raise ConfigError(
            f"invalid value for 'num_devices': {requested} (allowed: 0 = all, or 1 to {available}, "
            f"the JAX devices found: {jax.devices()[0].platform} x {available})"
        )
    return requested


def check_env_split(num_envs: int, num_devices: int) -> None:
    """Each device must get the same number of envs."""
    if num_envs % num_devices:
        raise ConfigError(
            f"invalid value for 'num_envs': {num_envs} (allowed: a multiple of the {num_devices} devices "
            f"the envs are split over; or set num_devices to a divisor of it)"
        )


def make_mesh(num_devices: int, axis: str) -> Mesh:
    """A 1-D mesh over the first ``num_devices`` devices (all hosts' devices when distributed)."""
    return Mesh(np.asarray(jax.devices()[:num_devices]), (axis,))


def _leading_axis_sharding(mesh: Mesh, axis: str, size: int):
    """Sharding for one leaf: split its leading axis if it has ``size`` rows, else replicate."""
    split = NamedSharding(mesh, PartitionSpec(axis))
    replicated = NamedSharding(mesh, PartitionSpec())

    def for_leaf(leaf) -> NamedSharding:
        shape = getattr(leaf, "shape", ())
        return split if len(shape) >= 1 and shape[0] == size else replicated

    return for_leaf


def env_state_shardings(state: Any, mesh: Mesh, num_envs: int) -> Any:
    """Shardings for a train state (or its `jax.eval_shape`): per-env fields split, the rest replicated.

    The per-env fields are the state's attributes named in `PER_ENV_FIELDS`; within them
    a leaf is split along its leading axis when that axis has ``num_envs`` rows (a
    scalar PRNG key inside ``env_state`` stays replicated).
    """
    replicated = NamedSharding(mesh, PartitionSpec())
    per_env = _leading_axis_sharding(mesh, ENV_AXIS, num_envs)
    shardings = jax.tree.map(lambda _: replicated, state)
    updates = {
        name: jax.tree.map(per_env, getattr(state, name)) for name in PER_ENV_FIELDS if hasattr(state, name)
    }
    return shardings.replace(**updates) if updates else shardings


def point_shardings(states: Any, mesh: Mesh) -> Any:
    """Shardings for a stacked sweep state: every leaf split along its leading (grid point) axis."""
    split = NamedSharding(mesh, PartitionSpec(POINT_AXIS))
    return jax.tree.map(lambda _: split, states)


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


def device_count_of(array: jax.Array) -> int:
    """How many devices hold a piece of ``array`` (for tests and logs)."""
    return len(array.sharding.device_set)


def init_state(trainer: Trainer, init_key: jax.Array, num_devices: int, num_envs: int):
    """The initial train state, on one device or already sharded over ``num_devices``.

    Returns:
      (state, shardings): ``shardings`` is None on one device, else the state's
      `env_state_shardings`, for `compile_iteration`.
    """
    if num_devices == 1:
        return jax.jit(trainer.init)(init_key), None
    check_env_split(num_envs, num_devices)
    mesh = make_mesh(num_devices, ENV_AXIS)
    shardings = env_state_shardings(jax.eval_shape(trainer.init, init_key), mesh, num_envs)
    return jax.jit(trainer.init, out_shardings=shardings)(init_key), shardings


def shard_state(state: Any, num_devices: int, num_envs: int):
    """An existing state (e.g. restored from a checkpoint) placed as `init_state` places a new one.

    Returns:
      (state, shardings), shardings None on one device.
    """
    if num_devices == 1:
        return state, None
    check_env_split(num_envs, num_devices)
    shardings = env_state_shardings(state, make_mesh(num_devices, ENV_AXIS), num_envs)
    return place(state, shardings), shardings


def point_device_count(num_points: int, available: int) -> int:
    """The largest device count up to `available` that divides the points (each device runs whole points)."""
    return max(d for d in range(1, available + 1) if num_points % d == 0)


def init_points(trainer: Trainer, init_keys: jax.Array, hparams: Any, num_devices: int):
    """The stacked initial states of a sweep's points, ``vmap(trainer.init)``, split over the devices.

    Returns:
      (states, shardings): ``shardings`` is None on one device, else `point_shardings`.
    """
    init = vmap_points(trainer.init)
    if num_devices == 1:
        return jax.jit(init)(init_keys, hparams), None
    mesh = make_mesh(num_devices, POINT_AXIS)
    shardings = point_shardings(jax.eval_shape(init, init_keys, hparams), mesh)
    return jax.jit(init, out_shardings=shardings)(init_keys, hparams), shardings


def shard_points(states: Any, num_devices: int):
    """Stacked sweep states (e.g. restored from a checkpoint) placed as `init_points` places new ones."""
    if num_devices == 1:
        return states, None
    shardings = point_shardings(states, make_mesh(num_devices, POINT_AXIS))
    return place(states, shardings), shardings


def compile_iteration(trainer: Trainer, state: Any, shardings: Any = None, points: bool = False):
    """``iteration(state) -> (state, metrics)`` compiled; the state's buffers are donated.

    With ``points`` the state is a sweep's stack of states and the iteration is
    ``vmap(trainer.iteration)``. With ``shardings`` (from `init_state` or
    `init_points`) the state keeps them in and out; a run's metrics are replicated, a
    sweep's split like its points. XLA's SPMD partitioner splits the work over the
    devices.
    """
    step = vmap_points(trainer.iteration) if points else trainer.iteration
    if shardings is None:
        return jax.jit(step, donate_argnums=0).lower(state).compile()
    mesh = jax.tree.leaves(shardings)[0].mesh
    metrics = NamedSharding(mesh, PartitionSpec(POINT_AXIS)) if points else replicated(mesh)
    iteration = jax.jit(step, in_shardings=(shardings,), out_shardings=(shardings, metrics), donate_argnums=0)
    return iteration.lower(state).compile()


def check_devices(cfg: Any, split_envs: bool = True) -> bool:
    """Initialises multi-host JAX if asked and checks the device split before anything is written.

    Returns whether this process writes the outputs (process 0 of a distributed run).
    """
    maybe_initialize_distributed(cfg.distributed)
    num_devices = resolve_num_devices(cfg.num_devices, cfg.env)
    check_host_pool(cfg.env, cfg.num_devices, num_devices, cfg.distributed)
    if split_envs:
        check_env_split(cfg.num_envs, num_devices)
        check_device_split(num_devices)
    return is_writer()


def check_host_pool(env: str, requested: int, num_devices: int, distributed: bool) -> None:
    """A Gymnasium env's copies live in one pool of this process and step in one host call per
    iteration (`coherent_jax.envs.host_gym`): one device, one process. Refused in one line."""
    if check_task(env).backend != "gym":
        return
    if distributed:
        raise ConfigError(
            f"invalid value for 'distributed': true with env={env} "
            "(allowed: false; a Gymnasium env's copies step in one pool of one process)"
        )
    if num_devices > 1:
        raise ConfigError(
            f"invalid value for 'num_devices': {requested} ({num_devices} devices) with env={env} "
            "(allowed: 1; a Gymnasium env's copies step in one host pool, on one device)"
        )


def maybe_initialize_distributed(enabled: bool) -> None:
    """`initialize` once, before any other JAX call, when ``enabled``."""
    if enabled:
        initialize()


# --- several processes: start-up (worker side) ----------------------------------------------------


def initialize() -> None:
    """`jax.distributed.initialize()` with gloo collectives on CPU and this module's timeouts.

    Must run before any other JAX call. Raises `ConfigError` (one line) when JAX
    cannot tell the coordinator, process count or id; an unreachable coordinator
    ends the process from the runtime (see `coherent_jax.run.multihost.supervise`).
    """
    kwargs: dict[str, Any] = {}
    for key, name in (("num_processes", "JAX_NUM_PROCESSES"), ("process_id", "JAX_PROCESS_ID")):
        text = os.environ.get(name, "").strip()
        if text:
            if not text.isdigit():
                raise ConfigError(f"invalid value for {name}: {text!r} (allowed: a whole number >= 0)")
            kwargs[key] = int(text)
    init_s = _timeout(INIT_TIMEOUT_ENV, DEFAULT_INIT_TIMEOUT_S)
    heartbeat_s = _timeout(HEARTBEAT_TIMEOUT_ENV, DEFAULT_HEARTBEAT_TIMEOUT_S)
    if "JAX_CPU_COLLECTIVES_IMPLEMENTATION" not in os.environ:
        # Without it, a CPU computation across processes fails (no cross-process collectives).
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    try:
        jax.distributed.initialize(
            initialization_timeout=init_s,
            heartbeat_timeout_seconds=heartbeat_s,
            # At a normal end all processes reach the shutdown barrier within one iteration.
            shutdown_timeout_seconds=max(heartbeat_s, 10),
            **kwargs,
        )
    except (ValueError, RuntimeError, TypeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ConfigError(
            f"invalid value for 'distributed': True ({first}) (allowed: false, or true on a cluster JAX "
            "detects or with JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES and JAX_PROCESS_ID set)"
        ) from None


def is_writer() -> bool:
    """Whether this process writes the run's files (process 0; the only process when not distributed)."""
    return jax.process_index() == 0


def check_device_split(num_devices: int) -> None:
    """Several processes must all take part: the mesh has to span every process's devices."""
    if jax.process_count() > 1 and num_devices != jax.device_count():
        raise ConfigError(
            f"invalid value for 'num_devices' with distributed=true: {num_devices} devices used of "
            f"{jax.device_count()} (allowed: 0 = all devices of all {jax.process_count()} processes; "
            "for a sweep, a number of grid points that is a multiple of them)"
        )


# --- host copies and placement --------------------------------------------------------------------


def to_host(tree: Any) -> Any:
    """The pytree's arrays as numpy arrays holding their whole global value.

    An array whose rows are split over several processes is gathered from all of
    them (a collective: every process must call this at the same point); arrays a
    process holds whole (replicated, or single-process) are copied without one.
    """

    def whole(x: Any) -> Any:
        if isinstance(x, jax.Array) and not (x.is_fully_addressable or x.is_fully_replicated):
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(jax.device_get(x))

    return jax.tree.map(whole, tree)


def place(tree: Any, shardings: Any) -> Any:
    """Host arrays (the same in every process) put on the devices as global arrays of `shardings`.

    Each process fills only its own devices' pieces, so this works whether or not
    the sharding spans other processes' devices.
    """

    def put(x: Any, sharding: Any) -> jax.Array:
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(put, tree, shardings)


# --- a checkpoint's state as bytes ----------------------------------------------------------------


def state_to_bytes(state: Any) -> bytes:
    """The leaves of the state pytree, in tree order, as flax msgpack.

    A state spread over several processes is gathered first: every process must call this.

    Leaves rather than the tree itself: the physics state of an MJX environment is a
    pytree that flax's serialisation does not know, and the tree structure is
    rebuilt from the trainer's own template on restore.
    """
    leaves = jax.tree_util.tree_leaves(to_host(state))
    return serialization.msgpack_serialize({str(i): np.asarray(x) for i, x in enumerate(leaves)})


def restore_state(template: Any, state_bytes: bytes, path: Path) -> Any:
    """The state pytree of a checkpoint, shaped like `template` (checked leaf by leaf).

    `template` may hold arrays or ``jax.ShapeDtypeStruct``s (``jax.eval_shape`` of
    the trainer's ``init``).
    """
    try:
        stored = serialization.msgpack_restore(state_bytes)
        leaves = [np.asarray(stored[str(i)]) for i in range(len(stored))]
    except Exception as exc:  # noqa: BLE001
        raise CheckpointError(f"checkpoint {str(path)!r}: unreadable state ({exc})") from None
    flat_t, treedef = jax.tree_util.tree_flatten_with_path(template)
    if len(flat_t) != len(leaves):
        raise CheckpointError(
            f"checkpoint {str(path)!r} has {len(leaves)} arrays, this trainer {len(flat_t)}"
        )
    for (where, t), s in zip(flat_t, leaves, strict=True):
        if s.shape != tuple(t.shape) or s.dtype != t.dtype:
            raise CheckpointError(
                f"checkpoint {str(path)!r}: {jax.tree_util.keystr(where)} is {s.dtype}{list(s.shape)}, "
                f"this trainer expects {t.dtype}{list(t.shape)}"
            )
    return jax.device_put(jax.tree_util.tree_unflatten(treedef, leaves))


# --- agreement ------------------------------------------------------------------------------------


def largest(value: int) -> int:
    """The largest of the processes' `value`s, in every process (a collective when distributed).

    E.g. the signal number of a stop request (0: none), so that all stop together.
    """
    if jax.process_count() == 1:
        return int(value)
    return int(np.max(multihost_utils.process_allgather(np.asarray([value], np.int32))))


def from_writer(flag: bool) -> bool:
    """Process 0's `flag`, in every process (a collective when distributed)."""

    if jax.process_count() == 1:
        return bool(flag)
    return bool(multihost_utils.broadcast_one_to_all(np.asarray(flag, np.int32)))
