"""The JAX side of a ``distributed=true`` worker (`coherent_jax.run.multihost` is the rest):
start-up, host copies and placement, agreement between the processes."""

from __future__ import annotations

import os
from typing import Any

import jax
import numpy as np
from jax.experimental import multihost_utils

from coherent_jax.config import ConfigError
from coherent_jax.run.multihost import (
    DEFAULT_HEARTBEAT_TIMEOUT_S,
    DEFAULT_INIT_TIMEOUT_S,
    HEARTBEAT_TIMEOUT_ENV,
    INIT_TIMEOUT_ENV,
    _timeout,
)

# --- start-up (worker side) ------------------------------------------------------------------


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


# --- host copies and placement ---------------------------------------------------------------


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


# --- agreement -------------------------------------------------------------------------------


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
