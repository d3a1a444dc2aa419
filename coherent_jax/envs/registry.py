"""Registry of tasks by name: Gymnasium's MuJoCo v5 tasks, Brax's re-creations, the
DeepMind Control Suite, a test task.

* The standard tasks papers report on are Gymnasium's MuJoCo v5 tasks, registered by
  their Gymnasium ids (``HalfCheetah-v5``, ...) and by the short names a user types
  (``halfcheetah``, ...). They run on native MuJoCo (`coherent_jax.envs.gym_v5`).
* Brax's MJX re-creations of them (``brax-halfcheetah``, ...) are different tasks
  (other solver settings, contacts, integrators, reward details), kept as the fast
  path for accelerators. Each has its own solver settings: the line search of
  MuJoCo's Newton solver dominates the cost of an MJX step on CPU, so tasks whose
  dynamics tolerate it run with fewer line-search iterations (what Brax itself does
  for ant and humanoid). ``docs/benchmarks.md`` has the measurements behind this.
* The DeepMind Control Suite (``dmc-cartpole_swingup_sparse``, ...), through MuJoCo
  Playground's MJX ports (``playground`` on PyPI, imported only when such a task is
  built): dm_control's tasks with rewards in [0, 1] per step, 1000-step episodes and
  no terminations, several of them sparse, where exploration matters most.
"""

from __future__ import annotations

import dataclasses
import os
import re
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
      playground_id: the MuJoCo Playground id of a DeepMind Control Suite task.
    """

    brax_name: str
    ls_iterations: int | None
    episode_length: int = 1000
    description: str = ""
    backend: str = "mjx"
    gymnasium_id: str = ""
    playground_id: str = ""


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

# Why MJX cannot run a Gymnasium task (``physics=mjx`` is refused with this reason); the
# others run their own model on MJX (`coherent_jax.envs.mjx_physics`).
MJX_REFUSAL: Mapping[str, str] = {
    "Humanoid-v5": "its PGS solver is not implemented in MJX; Brax's MJX re-creation is 'brax-humanoid'",
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

# The DeepMind Control Suite as MuJoCo Playground 0.2.0 ports it
# (``mujoco_playground.dm_control_suite.ALL_ENVS``), by dm_control's domain and task
# names. Sparse: the reward is 1 inside the target set and 0 outside (dm_control's
# ``tolerance`` with no margin), so a policy learns only once its exploration gets there.
_DMC_SPARSE = {
    "AcrobotSwingupSparse": "acrobot swing-up, reward 1 with the tip in the target",
    "BallInCup": "swing a ball on a string into a cup, reward 1 with the ball in it",
    "CartpoleBalanceSparse": "cart-pole kept upright from near upright, reward 1 while balanced",
    "CartpoleSwingupSparse": "cart-pole swing-up from hanging, reward 1 while upright and centred",
    "FingerTurnEasy": "turn a hinged body to a target angle, wide target",
    "FingerTurnHard": "turn a hinged body to a target angle, narrow target",
    "ReacherEasy": "2-link arm to a random target, large target",
    "ReacherHard": "2-link arm to a random target, small target",
}
_DMC_DENSE = {
    "AcrobotSwingup": "acrobot swing-up, shaped reward",
    "CartpoleBalance": "cart-pole balance, shaped reward",
    "CartpoleSwingup": "cart-pole swing-up, shaped reward",
    "CheetahRun": "2D cheetah, run at 10 m/s",
    "FingerSpin": "spin a hinged body with a finger",
    "FishSwim": "3D fish swims to a target",
    "HopperHop": "one-legged hopper, hop forward",
    "HopperStand": "one-legged hopper, stand up",
    "HumanoidRun": "3D humanoid, run",
    "HumanoidStand": "3D humanoid, stand",
    "HumanoidWalk": "3D humanoid, walk",
    "PendulumSwingup": "pendulum swing-up, reward 1 near upright",
    "PointMass": "2D point mass to the origin",
    "SwimmerSwimmer6": "6-link swimmer to a target",
    "WalkerRun": "2D biped, run",
    "WalkerStand": "2D biped, stand",
    "WalkerWalk": "2D biped, walk",
}


def dmc_name(playground_id: str) -> str:
    """``CartpoleSwingupSparse`` -> ``dmc-cartpole_swingup_sparse`` (dm_control's names, snake case)."""
    return "dmc-" + re.sub(r"(?<!^)(?=[A-Z])", "_", playground_id).lower()


def _dmc_spec(playground_id: str) -> TaskSpec:
    sparse = playground_id in _DMC_SPARSE
    what = _DMC_SPARSE[playground_id] if sparse else _DMC_DENSE[playground_id]
    return TaskSpec(
        "",
        None,
        description=f"DeepMind Control {'(sparse) ' if sparse else ''}{playground_id}: {what}",
        playground_id=playground_id,
    )


DMC_SPARSE_TASKS = tuple(dmc_name(t) for t in sorted(_DMC_SPARSE))

TASKS: Mapping[str, TaskSpec] = {
    **{short: _gym_spec(gym_id) for short, gym_id in SHORT_NAMES.items()},
    **{gym_id: _gym_spec(gym_id) for gym_id in SHORT_NAMES.values()},
    **_BRAX,
    **{dmc_name(t): _dmc_spec(t) for t in sorted({**_DMC_SPARSE, **_DMC_DENSE})},
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
    """Builds the raw (unwrapped, unbatched) environment of task `name` with Brax's interface
    (``reset(key)``, ``step(state, action)``, states with ``obs``, ``reward``, ``done``): a
    ``brax-*`` task, a ``dmc-*`` task (Playground's env) or ``pointmass``; Gymnasium's
    tasks are not Brax environments."""
    spec = check_task(name)
    if spec.playground_id:
        return make_playground_env(spec.playground_id, **kwargs)
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


def make_playground_env(playground_id: str, **config_overrides: Any):
    """MuJoCo Playground's DeepMind Control env ``playground_id`` on MJX's JAX implementation.

    Playground 0.2.0 defaults to MJX's Warp implementation, which steps a fixed batch of
    worlds of its own and does not ``vmap``; ``impl="jax"`` is plain MJX, vmapped here like
    Brax's envs. Everything else is Playground's default config (1000-step episodes,
    its control and simulation steps).
    """
    try:
        with _quiet_stdio(force=True):  # Warp prints its kernel-cache lines on import
            from mujoco_playground import registry as playground
    except ImportError as err:  # pragma: no cover - a dependency of the package
        raise UnknownTaskError(
            f"the DeepMind Control tasks need MuJoCo Playground (pip install playground): {err}"
        ) from None
    with _quiet_stdio(force=True):
        return playground.load(playground_id, config_overrides={"impl": "jax", **config_overrides})


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
