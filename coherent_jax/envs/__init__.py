"""MuJoCo tasks through MJX: a registry by short name and a vectorized wrapper."""

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
