"""What a task is to the registry (`TaskSpec`), the names of a user's own tasks, and their
refusals; no JAX.

`TaskSpec` says how to build one task; ``env=MODULE:NAME`` and ``env=path/to/file.py:NAME``
name a task of the user's own, ``env=gym:ID`` a registered Gymnasium env (`coherent_jax.envs.user`
loads them). A bad one is refused in one line (`refuse`: `TaskDefinitionError` naming the task
and the problem), as is a module of the user's that does not import (`import_module`).

Apart from the registry (`coherent_jax.envs.registry`): the registry's `check_task` loads a
user's task through `coherent_jax.envs.user`, which builds on this module, as do the kinds'
loaders (`coherent_jax.envs.gym_source`, `coherent_jax.envs.jax_env`); in one module, the
registry would import itself back through them.
"""

from __future__ import annotations

import dataclasses
import importlib
import re
from pathlib import Path
from types import ModuleType
from typing import NoReturn


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
        `coherent_jax.envs.native_ports`).
      goal: the task terminates exactly when it reaches its goal, so the fraction of episodes
        that terminate is logged as ``train/goal_reached`` and ``eval/goal_reached``.
      max_episode_length: the longest ``episode_length`` the task can run (a Gymnasium env
        that truncates its own episodes); None: any.
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
    max_episode_length: int | None = None


class UnknownTaskError(ValueError):
    """Raised for a task name that is not in the registry."""


class TaskDefinitionError(ValueError):
    """A task of the user's (``env=MODULE:NAME``) that cannot be loaded or breaks the contract;
    the message names the task and the problem (`coherent_jax.envs.user`)."""


# ``env=MODULE:NAME``: attribute NAME of the importable module MODULE is a task of the user's
# (`coherent_jax.envs.user`), imported only when the task is built or checked;
# ``env=path/to/file.py:NAME``: the same, of the Python file at that path.
_USER_TASK = re.compile(r"(?P<source>[A-Za-z_]\w*(\.[A-Za-z_]\w*)*|[^:]+\.py):(?P<name>[A-Za-z_]\w*)")
# ``env=gym:ID`` (a registered Gymnasium id) or ``env=gym:MODULE:ID`` (MODULE imported first for
# its registrations): a Gymnasium env stepped on the host (`coherent_jax.envs.gym_source`).
_GYM_ID = re.compile(r"gym:((?P<module>[A-Za-z_]\w*(\.[A-Za-z_]\w*)*):)?(?P<id>[A-Za-z_][\w./-]*)")
USER_TASK_FORM = (
    "MODULE:NAME or path/to/file.py:NAME (a task or gymnasium.Env of your own), "
    "or gym:ID / gym:MODULE:ID (a registered Gymnasium env), docs/tasks.md"
)


def is_gym_id(name: str) -> bool:
    """Whether `name` has the form ``gym:ID`` (``gym:Pendulum-v1``) or ``gym:MODULE:ID``."""
    return isinstance(name, str) and _GYM_ID.fullmatch(name) is not None


def gym_id_parts(name: str) -> tuple[str, str]:
    """(module to import first or "", Gymnasium id) of ``gym:[MODULE:]ID``."""
    match = _GYM_ID.fullmatch(name)
    if match is None:
        raise TaskDefinitionError(f"task {name!r}: not of the form gym:ID or gym:MODULE:ID")
    return match.group("module") or "", match.group("id")


def is_user_task(name: str) -> bool:
    """Whether `name` is an env of the user's own: ``MODULE:NAME`` (``examples.reacher_task:reacher``),
    ``FILE.py:NAME`` (``examples/reacher_task.py:reacher``) or a Gymnasium id ``gym:[MODULE:]ID``."""
    return isinstance(name, str) and (_USER_TASK.fullmatch(name) is not None or is_gym_id(name))


def user_task_parts(name: str) -> tuple[str, str, bool]:
    """(module or file, attribute, whether it is a file's path) of a user's task `name`."""
    match = _USER_TASK.fullmatch(name)
    if match is None:
        raise TaskDefinitionError(f"task {name!r}: not of the form {USER_TASK_FORM}")
    source = match.group("source")
    return source, match.group("name"), source.endswith(".py")


def task_label(name: str) -> str:
    """`name` as a file name can hold it: a file's task by the file's stem (``reacher_task:reacher``)."""
    if not is_user_task(name) or is_gym_id(name):
        return name
    source, attr, is_file = user_task_parts(name)
    return f"{Path(source).stem}:{attr}" if is_file else name


def first_line(exc: BaseException) -> str:
    """``Type: first line of the message`` of an exception, for one-line refusals."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


def refuse(name: str, problem: str) -> NoReturn:
    """Raises `TaskDefinitionError` naming the task ``name`` and the problem."""
    raise TaskDefinitionError(f"task {name!r}: {problem}")


def import_module(name: str, module_name: str) -> ModuleType:
    """The importable module ``module_name`` of task ``name``; any error of it refuses the task."""
    try:
        return importlib.import_module(module_name)
    except Exception as exc:  # any error of the user's module is a bad task definition
        refuse(name, f"cannot import module {module_name!r} ({first_line(exc)}; is it on PYTHONPATH?)")
