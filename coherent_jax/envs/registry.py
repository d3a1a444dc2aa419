"""Registry of MuJoCo tasks by short name.

Every task is a Brax MJX environment (`brax.envs`, backend ``mjx``) with its own
solver settings: the line search of MuJoCo's Newton solver dominates the cost of
an MJX step on CPU, so tasks whose dynamics tolerate it run with fewer line-search
iterations (what Brax itself does for ant and humanoid). ``DESIGN.md`` §5 has the
measurements behind these numbers.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import warnings
from collections.abc import Mapping
from typing import Any


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """How to build one task.

    Attributes:
      brax_name: name of the environment in ``brax.envs`` (or, for backend ``jax``,
        of this package's own pure-JAX task).
      ls_iterations: MuJoCo solver line-search iterations (``opt.ls_iterations``);
        None keeps the model's own value.
      episode_length: default time limit in environment steps.
      description: one line for ``--help`` and the README.
      backend: Brax physics pipeline; ``mjx`` except where Brax has no MJX model;
        ``jax`` for an analytic task with no physics engine.
    """

    brax_name: str
    ls_iterations: int | None
    episode_length: int = 1000
    description: str = ""
    backend: str = "mjx"


TASKS: Mapping[str, TaskSpec] = {
    "halfcheetah": TaskSpec("halfcheetah", 4, description="2D cheetah, run forward (17 obs, 6 act)"),
    "hopper": TaskSpec("hopper", 4, description="2D one-legged hopper (11 obs, 3 act)"),
    "walker2d": TaskSpec("walker2d", 4, description="2D biped walker (17 obs, 6 act)"),
    "ant": TaskSpec("ant", None, description="3D quadruped (27 obs, 8 act); Brax sets ls=4"),
    "humanoid": TaskSpec("humanoid", None, description="3D humanoid (244 obs, 17 act); Brax sets ls=4"),
    "inverted_pendulum": TaskSpec("inverted_pendulum", None, description="cart-pole balance (4 obs, 1 act)"),
    "inverted_double_pendulum": TaskSpec(
        "inverted_double_pendulum", None, description="double cart-pole balance (8 obs, 1 act)"
    ),
    "reacher": TaskSpec("reacher", None, description="2-link arm reaching a target (11 obs, 2 act)"),
    # Brax's swimmer refuses the MJX backend; its generalized pipeline runs the same MJCF.
    "swimmer": TaskSpec(
        "swimmer", None, description="3-link swimmer (8 obs, 2 act); Brax generalized", backend="generalized"
    ),
    # Not MuJoCo: an analytic task in pure JAX for fast tests of the machinery.
    "pointmass": TaskSpec(
        "pointmass", None, description="analytic 2D point mass to a goal (6 obs, 2 act)", backend="jax"
    ),
}


class UnknownTaskError(ValueError):
    """Raised for a task name that is not in the registry."""


def check_task(name: str) -> TaskSpec:
    """Returns the spec of `name`, or raises naming the valid tasks."""
    if name not in TASKS:
        raise UnknownTaskError(f"unknown env {name!r}; valid envs: {', '.join(sorted(TASKS))}")
    return TASKS[name]


def make_brax_env(name: str, **kwargs: Any):
    """Builds the raw (unwrapped, unbatched) Brax MJX environment for task `name`."""
    spec = check_task(name)
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
