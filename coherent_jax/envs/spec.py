"""What a task is to the registry, and the names of a user's own tasks; no JAX.

`TaskSpec` says how to build one task; ``env=MODULE:NAME`` and ``env=path/to/file.py:NAME``
name a task of the user's own (`coherent_jax.envs.user_task` loads it). The registry
(`coherent_jax.envs.registry`) and the user-task loader both build on this module.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """How to build one task.

    Attributes:
      brax_name: name of the environment in ``brax.envs`` (for backend ``jax``, of
        this package's own pure-JAX task; empty for Gymnasium's tasks).
      ls_iterations: MuJoCo solver line-search iterations (``opt.ls_iterations``) of
        the MJX task; None keeps the model's own value.
      episode_length: default time limit in environment steps.
      description: one line for ``--help`` and the README.
      backend: ``native`` for Gymnasium's tasks (native MuJoCo); for Brax's, its physics
        pipeline: ``mjx`` except where Brax has no MJX model; ``jax`` for an analytic
        task with no physics engine.
      gymnasium_id: the Gymnasium id of a Gymnasium task (MuJoCo's on native MuJoCo, or a
        classic task in pure JAX, backend ``jax``).
      playground_id: the MuJoCo Playground id of a DeepMind Control Suite task.
      native: whether native MuJoCo runs it (its formulas: `coherent_jax.envs.gym_v5`,
        `coherent_jax.envs.brax_native`, `coherent_jax.envs.dmc_native`).
      goal: the task terminates exactly when it reaches its goal, so the fraction of episodes
        that terminate is logged as ``train/goal_reached`` and ``eval/goal_reached``.
    """

    brax_name: str
    ls_iterations: int | None
    episode_length: int = 1000
    description: str = ""
    backend: str = "mjx"
    gymnasium_id: str = ""
    playground_id: str = ""
    native: bool = False
    goal: bool = False


class UnknownTaskError(ValueError):
    """Raised for a task name that is not in the registry."""


class TaskDefinitionError(ValueError):
    """A task of the user's (``env=MODULE:NAME``) that cannot be loaded or breaks the contract;
    the message names the task and the problem (`coherent_jax.envs.user_task`)."""


# ``env=MODULE:NAME``: attribute NAME of the importable module MODULE is a task of the user's
# (`coherent_jax.envs.user_task`), imported only when the task is built or checked;
# ``env=path/to/file.py:NAME``: the same, of the Python file at that path.
_USER_TASK = re.compile(r"(?P<source>[A-Za-z_]\w*(\.[A-Za-z_]\w*)*|[^:]+\.py):(?P<name>[A-Za-z_]\w*)")
USER_TASK_FORM = "MODULE:NAME or path/to/file.py:NAME (a task of your own, docs/tasks.md)"


def is_user_task(name: str) -> bool:
    """Whether `name` has the form ``MODULE:NAME`` (``examples.reacher_task:reacher``) or
    ``FILE.py:NAME`` (``examples/reacher_task.py:reacher``)."""
    return isinstance(name, str) and _USER_TASK.fullmatch(name) is not None


def user_task_parts(name: str) -> tuple[str, str, bool]:
    """(module or file, attribute, whether it is a file's path) of a user's task `name`."""
    match = _USER_TASK.fullmatch(name)
    if match is None:
        raise TaskDefinitionError(f"task {name!r}: not of the form {USER_TASK_FORM}")
    source = match.group("source")
    return source, match.group("name"), source.endswith(".py")


def task_label(name: str) -> str:
    """`name` as a file name can hold it: a file's task by the file's stem (``reacher_task:reacher``)."""
    if not is_user_task(name):
        return name
    source, attr, is_file = user_task_parts(name)
    return f"{Path(source).stem}:{attr}" if is_file else name
