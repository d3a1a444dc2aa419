"""MuJoCo tasks: a registry by short name and a vectorized wrapper, on MJX or native MuJoCo."""

from coherent_jax.envs.native import NATIVE_TASKS, PHYSICS, NativePhysics, PhysicsError, resolve_physics
from coherent_jax.envs.registry import (
    TASKS,
    TaskSpec,
    UnknownTaskError,
    check_task,
    env_sizes,
    make_brax_env,
)
from coherent_jax.envs.vec_env import EnvState, StepOutcome, VecEnv

__all__ = [
    "NATIVE_TASKS",
    "PHYSICS",
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
