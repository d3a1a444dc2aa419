"""MuJoCo tasks: a registry by short name and a vectorized wrapper, on MJX or native MuJoCo.

The registry (`coherent_jax.envs.registry`: the tasks, and which engine runs each) is
free of JAX, so the config reads it without loading JAX; the engines, the wrapper and
the names a task of the user's own is written with (`MjcfTask`, `Kinematics`) are imported
from here on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

from coherent_jax.envs.registry import (
    NATIVE_TASKS,
    PHYSICS,
    TASKS,
    PhysicsError,
    TaskSpec,
    UnknownTaskError,
    check_task,
    resolve_physics,
)

_LAZY = {
    "Kinematics": "coherent_jax.envs.mujoco_task",
    "MjcfTask": "coherent_jax.envs.user",
    "NativePhysics": "coherent_jax.envs.physics",
    "EnvState": "coherent_jax.envs.vec_env",
    "StepOutcome": "coherent_jax.envs.vec_env",
    "VecEnv": "coherent_jax.envs.vec_env",
    "env_sizes": "coherent_jax.envs.brax_env",
    "make_brax_env": "coherent_jax.envs.brax_env",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "NATIVE_TASKS",
    "PHYSICS",
    "Kinematics",
    "MjcfTask",
    "NativePhysics",
    "PhysicsError",
    "resolve_physics",
    "TASKS",
    "EnvState",
    "StepOutcome",
    "TaskSpec",
    "UnknownTaskError",
    "VecEnv",
    "check_task",
    "env_sizes",
    "make_brax_env",
]
