"""Registry of tasks by name: Gymnasium's MuJoCo v5 tasks, Brax's re-creations, a test task.

* The standard tasks papers report on are Gymnasium's MuJoCo v5 tasks, registered by
  their Gymnasium ids (``HalfCheetah-v5``, ...) and by the short names a user types
  (``halfcheetah``, ...). They run on native MuJoCo (`coherent_jax.envs.gym_v5`).
* Brax's MJX re-creations of them (``brax-halfcheetah``, ...) are different tasks
  (other solver settings, contacts, integrators, reward details), kept as the fast
  path for accelerators. Each has its own solver settings: the line search of
  MuJoCo's Newton solver dominates the cost of an MJX step on CPU, so tasks whose
  dynamics tolerate it run with fewer line-search iterations (what Brax itself does
  for ant and humanoid). ``DESIGN.md`` §5 has the measurements behind these numbers.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import warnings
from collections.abc import Mapping
from typing import Any

from coherent_jax.envs.gym_v5 import EPISODE_LENGTH, SHORT_NAMES


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
      gymnasium_id: the Gymnasium id of a Gymnasium task.
    """

    brax_name: str
    ls_iterations: int | None
    episode_length: int = 1000
    description: str = ""
    backend: str = "mjx"
    gymnasium_id: str = ""


_GYM_DESCRIPTIONS = {
    "HalfCheetah-v5": "2D cheetah, run forward (17 obs, 6 act)",
    "Hopper-v5": "2D one-legged hopper (11 obs, 3 act)",
    "Walker2d-v5": "2D biped walker (17 obs, 6 act)",
    "Ant-v5": "3D quadruped, contact forces observed (105 obs, 8 act)",
    "Humanoid-v5": "3D humanoid (348 obs, 17 act)",
    "Swimmer-v5": "3-link swimmer in a viscous fluid (8 obs, 2 act)",
    "InvertedPendulum-v5": "cart-pole balance (4 obs, 1 act)",
    "InvertedDoublePendulum-v5": "double cart-pole balance (9 obs, 1 act)",
    "Reacher-v5": "2-link arm reaching a target, 50-step episodes (10 obs, 2 act)",
}

# Why MJX cannot run a Gymnasium task here (``physics=mjx`` is refused with this reason).
MJX_REFUSAL: Mapping[str, str] = {
    gym_id: (
        "its PGS solver is not implemented in MJX"
        if gym_id == "Humanoid-v5"
        else "Gymnasium's tasks run on native MuJoCo only here"
    )
    + f"; Brax's MJX re-creation is 'brax-{short}'"
    for short, gym_id in SHORT_NAMES.items()
}


def _gym_spec(gym_id: str) -> TaskSpec:
    return TaskSpec(
        "",
        None,
        episode_length=EPISODE_LENGTH[gym_id],
        description=f"Gymnasium {gym_id}: {_GYM_DESCRIPTIONS[gym_id]}",
        backend="native",
        gymnasium_id=gym_id,
    )


_BRAX: Mapping[str, TaskSpec] = {
    "brax-halfcheetah": TaskSpec("halfcheetah", 4, description="Brax's 2D cheetah (17 obs, 6 act)"),
    "brax-hopper": TaskSpec("hopper", 4, description="Brax's 2D one-legged hopper (11 obs, 3 act)"),
    "brax-walker2d": TaskSpec("walker2d", 4, description="Brax's 2D biped walker (17 obs, 6 act)"),
    "brax-ant": TaskSpec("ant", None, description="Brax's 3D quadruped (27 obs, 8 act); Brax sets ls=4"),
    "brax-humanoid": TaskSpec(
        "humanoid", None, description="Brax's 3D humanoid (244 obs, 17 act); Brax sets ls=4"
    ),
    "brax-inverted_pendulum": TaskSpec(
        "inverted_pendulum", None, description="Brax's cart-pole balance (4 obs, 1 act)"
    ),
    "brax-inverted_double_pendulum": TaskSpec(
        "inverted_double_pendulum", None, description="Brax's double cart-pole balance (8 obs, 1 act)"
    ),
    "brax-reacher": TaskSpec(
        "reacher", None, description="Brax's 2-link arm reaching a target (11 obs, 2 act)"
    ),
    # Brax's swimmer refuses the MJX backend; its generalized pipeline runs the same MJCF.
    "brax-swimmer": TaskSpec(
        "swimmer",
        None,
        description="Brax's 3-link swimmer (8 obs, 2 act); Brax generalized",
        backend="generalized",
    ),
}

TASKS: Mapping[str, TaskSpec] = {
    **{short: _gym_spec(gym_id) for short, gym_id in SHORT_NAMES.items()},
    **{gym_id: _gym_spec(gym_id) for gym_id in SHORT_NAMES.values()},
    **_BRAX,
    # Not MuJoCo: an analytic task in pure JAX for fast tests of the machinery.
    "pointmass": TaskSpec(
        "pointmass", None, description="analytic 2D point mass to a goal (6 obs, 2 act)", backend="jax"
    ),
}


def brax_counterpart(name: str) -> str:
    """The Brax environment closest to task ``name``: itself, or for a Gymnasium task its
    Brax re-creation (``halfcheetah`` and ``HalfCheetah-v5`` -> ``brax-halfcheetah``)."""
    spec = check_task(name)
    if not spec.gymnasium_id:
        return name
    short = next(k for k, v in SHORT_NAMES.items() if v == spec.gymnasium_id)
    return f"brax-{short}"


class UnknownTaskError(ValueError):
    """Raised for a task name that is not in the registry."""


def check_task(name: str) -> TaskSpec:
    """Returns the spec of `name`, or raises naming the valid tasks of both families."""
    if name not in TASKS:
        raise UnknownTaskError(f"unknown env {name!r}; valid envs: {', '.join(TASKS)}")
    return TASKS[name]


def make_brax_env(name: str, **kwargs: Any):
    """Builds the raw (unwrapped, unbatched) Brax environment of task `name` (a ``brax-*`` task
    or ``pointmass``); Gymnasium's tasks are not Brax environments."""
    spec = check_task(name)
    if spec.gymnasium_id:
        short = next(s for s, g in SHORT_NAMES.items() if g == spec.gymnasium_id)
        raise UnknownTaskError(
            f"env {name!r} is Gymnasium's {spec.gymnasium_id} on native MuJoCo, not a Brax env; "
            f"Brax's re-creation is 'brax-{short}'"
        )
    if spec.backend == "jax":  # this package's own pure-JAX tasks
        from coherent_jax.envs.pointmass import PointMass

        return {"pointmass": PointMass}[spec.brax_name](**kwargs)
    # Brax prints a warning for its optional Warp backend on import; it is noise here.
    with _quiet_stdio():
        from brax import envs as brax_envs

    with warnings.catch_warnings():
        # Brax warns that its own pipelines are unmaintained; we use the MJX one.
        warnings.filterwarnings("ignore", message="Brax System, piplines")
        with _quiet_stdio(force=True):  # MuJoCo's compiler prints deprecation notes
            env = brax_envs.get_environment(spec.brax_name, backend=spec.backend, **kwargs)
    if spec.ls_iterations is not None:
        env.sys = env.sys.tree_replace({"opt.ls_iterations": spec.ls_iterations})
    return env


def env_sizes(env) -> tuple[int, int]:
    """(observation size, action size) of a Brax env without running it.

    Brax's ``observation_size`` property runs an eager reset, hundreds of small XLA
    compilations (about 20 s on this CPU); ``jax.eval_shape`` only traces it.
    """
    import jax

    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    return int(state.obs.shape[-1]), int(env.action_size)


class _quiet_stdio:
    """Silences file descriptors 1 and 2 (Brax's import of optional backends prints)."""

    def __init__(self, force: bool = False):
        self._force = force

    def __enter__(self):
        if "brax.envs" in sys.modules and not self._force:
            self._fds = None
            return self
        sys.stdout.flush()
        sys.stderr.flush()
        self._devnull = os.open(os.devnull, os.O_WRONLY)
        self._fds = (os.dup(1), os.dup(2))
        os.dup2(self._devnull, 1)
        os.dup2(self._devnull, 2)
        return self

    def __exit__(self, *exc):
        if self._fds is not None:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(self._fds[0], 1)
            os.dup2(self._fds[1], 2)
            for fd in (*self._fds, self._devnull):
                os.close(fd)
        return False
