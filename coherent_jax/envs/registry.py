"""Registry of tasks by name: Gymnasium's MuJoCo v5 tasks, Brax's re-creations, the
DeepMind Control Suite, Gymnasium's classic exploration tasks, a test task.

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
* Gymnasium's ``MountainCarContinuous-v0`` and ``Pendulum-v1`` (``mountain_car_continuous``,
  ``pendulum``), step for step in pure JAX (`coherent_jax.envs.brax_env`).
* A task of the user's own, ``env=MODULE:NAME``: an MJCF file and JAX formulas
  (`coherent_jax.envs.user`), run like Gymnasium's tasks on native MuJoCo or MJX; or
  any Gymnasium env, ``env=gym:ID`` or the user's ``gymnasium.Env`` as ``env=MODULE:NAME``,
  stepped on the host (`coherent_jax.envs.gym_source`, `coherent_jax.envs.host_gym`).

The registry is free of JAX, so the config reads it without loading JAX: a task's environment
is built elsewhere (`coherent_jax.envs.vec_env`, `coherent_jax.envs.brax_env`). `TaskSpec` and
the names of a user's tasks are in `coherent_jax.envs.spec`, below the loaders of users' tasks
that `check_task` calls (`coherent_jax.envs.user`).
"""

from __future__ import annotations

import re
from collections.abc import Mapping

from coherent_jax.envs.spec import (  # noqa: F401 - the registry's names too
    USER_TASK_FORM,
    TaskDefinitionError,
    TaskSpec,
    UnknownTaskError,
    is_user_task,
    task_label,
    user_task_parts,
)

# The names a user types for Gymnasium's standard tasks.
SHORT_NAMES: Mapping[str, str] = {
    "halfcheetah": "HalfCheetah-v5",
    "hopper": "Hopper-v5",
    "walker2d": "Walker2d-v5",
    "ant": "Ant-v5",
    "humanoid": "Humanoid-v5",
    "swimmer": "Swimmer-v5",
    "inverted_pendulum": "InvertedPendulum-v5",
    "inverted_double_pendulum": "InvertedDoublePendulum-v5",
    "reacher": "Reacher-v5",
}
# Gymnasium's registered max_episode_steps.
EPISODE_LENGTH: Mapping[str, int] = {g: 50 if g == "Reacher-v5" else 1000 for g in SHORT_NAMES.values()}


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
# others run their own model on MJX (`coherent_jax.envs.physics`).
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
        native=True,
    )


_BRAX: Mapping[str, TaskSpec] = {
    "brax-halfcheetah": TaskSpec(
        "halfcheetah", 4, description="Brax's 2D cheetah (17 obs, 6 act)", native=True
    ),
    "brax-hopper": TaskSpec(
        "hopper", 4, description="Brax's 2D one-legged hopper (11 obs, 3 act)", native=True
    ),
    "brax-walker2d": TaskSpec(
        "walker2d", 4, description="Brax's 2D biped walker (17 obs, 6 act)", native=True
    ),
    "brax-ant": TaskSpec(
        "ant", None, description="Brax's 3D quadruped (27 obs, 8 act); Brax sets ls=4", native=True
    ),
    "brax-humanoid": TaskSpec(
        "humanoid", None, description="Brax's 3D humanoid (244 obs, 17 act); Brax sets ls=4"
    ),
    "brax-inverted_pendulum": TaskSpec(
        "inverted_pendulum", None, description="Brax's cart-pole balance (4 obs, 1 act)", native=True
    ),
    "brax-inverted_double_pendulum": TaskSpec(
        "inverted_double_pendulum",
        None,
        description="Brax's double cart-pole balance (8 obs, 1 act)",
        native=True,
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


# Playground's tasks native MuJoCo runs (`coherent_jax.envs.native_ports`): the ones MJX runs slowest.
_DMC_NATIVE = ("BallInCup", "FingerTurnHard")


def _dmc_spec(playground_id: str) -> TaskSpec:
    sparse = playground_id in _DMC_SPARSE
    what = _DMC_SPARSE[playground_id] if sparse else _DMC_DENSE[playground_id]
    return TaskSpec(
        "",
        None,
        description=f"DeepMind Control {'(sparse) ' if sparse else ''}{playground_id}: {what}",
        playground_id=playground_id,
        native=playground_id in _DMC_NATIVE,
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
    # Gymnasium's classic exploration tasks, step for step in pure JAX (`coherent_jax.envs.brax_env`).
    "mountain_car_continuous": TaskSpec(
        "mountain_car_continuous",
        None,
        episode_length=999,
        description="Gymnasium MountainCarContinuous-v0 in JAX: reach the hilltop, goal pays (2 obs, 1 act)",
        backend="jax",
        gymnasium_id="MountainCarContinuous-v0",
        goal=True,
    ),
    "pendulum": TaskSpec(
        "pendulum",
        None,
        episode_length=200,
        description="Gymnasium Pendulum-v1 in JAX: swing up and hold, dense cost (3 obs, 1 act)",
        backend="jax",
        gymnasium_id="Pendulum-v1",
    ),
}
# The classic tasks by Gymnasium id (Gymnasium's own env, not MuJoCo: `coherent_jax.evaluate`).
CLASSIC_IDS: Mapping[str, str] = {
    spec.gymnasium_id: name for name, spec in TASKS.items() if spec.backend == "jax" and spec.gymnasium_id
}


def brax_counterpart(name: str) -> str:
    """The Brax environment closest to task ``name``: itself, or for a Gymnasium task its
    Brax re-creation (``halfcheetah`` and ``HalfCheetah-v5`` -> ``brax-halfcheetah``)."""
    spec = check_task(name)
    if not spec.gymnasium_id or spec.backend != "native":  # not one of Gymnasium's MuJoCo tasks
        return name
    short = next(k for k, v in SHORT_NAMES.items() if v == spec.gymnasium_id)
    return f"brax-{short}"


def check_task(name: str) -> TaskSpec:
    """Returns the spec of `name`, or raises naming the valid tasks of both families.

    A ``MODULE:NAME`` task is imported and checked here (JAX and MuJoCo are loaded then);
    a bad one raises `TaskDefinitionError`."""
    if is_user_task(name):
        from coherent_jax.envs.user import (
            load_user_task,  # lazy: JAX and MuJoCo; this module has neither
        )

        return load_user_task(name).spec
    if name not in TASKS:
        raise UnknownTaskError(f"unknown env {name!r}; valid envs: {', '.join(TASKS)}, or {USER_TASK_FORM}")
    return TASKS[name]


# --- physics engines
PHYSICS = ("auto", "mjx", "native")
# MuJoCo threads per call (0 = every core). On the shared 2-core machine one thread
# was as fast as two or faster in 2 of 3 runs of `python -m benchmarks physics`
# (loaded machine: 25k vs 15k env steps/s at 64 halfcheetah envs); on a quiet moment
# two threads gave 41k vs 21k at 64 envs. A dedicated machine should try 0.
DEFAULT_THREADS = 1
# Every task native MuJoCo runs, by registry name: Gymnasium's (by id and by short name),
# six of Brax's and two of the DeepMind Control Suite's.
NATIVE_TASKS: tuple[str, ...] = tuple(name for name, spec in TASKS.items() if spec.native)


class PhysicsError(ValueError):
    """A physics backend that does not exist or does not support the task."""


def auto_physics(has_native: bool, backend: str) -> str:
    """What ``physics=auto`` picks for a MuJoCo task: native MuJoCo on a CPU when the task has it
    (faster there, see ``python -m benchmarks physics``), else MJX.

    On an accelerator (any `backend` but ``cpu``) always MJX: native MuJoCo is stepped on
    the host through a callback, which would put a host round trip into every step of the
    compiled iteration.
    """
    return "native" if has_native and backend == "cpu" else "mjx"


def resolve_physics(task: str, physics: str, backend: str | None = None) -> str:
    """The backend a task runs on: ``mjx`` or ``native`` (own-pipeline tasks keep theirs).

    ``native`` and ``mjx`` are taken as given where the task has them: Gymnasium's tasks and
    the user's own (``MODULE:NAME``) run on native MuJoCo, or their own model on MJX
    (`coherent_jax.envs.physics`) except where MJX cannot run it (refused with the
    reason); a Gymnasium env (``gym:ID``, or the user's ``gymnasium.Env``) on ``gym``, its
    own engine on the host, with ``auto`` or ``native``; Brax's re-creations and Playground's
    tasks on MJX, or native MuJoCo for those that have it. ``auto`` is `auto_physics` of the
    task and `backend` (default: JAX's, asked only then): on an accelerator it never picks the
    host callback, and a task MJX cannot run is refused there, naming ``physics=native``.
    Raises `PhysicsError` with a one-line message.
    """
    spec = check_task(task)
    if physics not in PHYSICS:
        raise PhysicsError(f"unknown physics {physics!r}; valid: {', '.join(PHYSICS)}")
    if spec.backend == "jax-env":  # a JAX env with Brax's interface runs on its own backend (jax_env.py)
        if physics != "auto":
            raise PhysicsError(
                f"physics={physics} does not apply to env {task!r}, a JAX environment that runs on "
                "its own backend (allowed: auto)"
            )
        return spec.backend
    if spec.backend == "gym":  # a Gymnasium env steps on the host, on its own engine
        if physics == "mjx":
            raise PhysicsError(f"physics=mjx does not support env {task!r}: Gymnasium envs step on the host")
        return "gym"
    if spec.backend == "native":  # Gymnasium's tasks and the user's: they all have native MuJoCo
        if physics == "auto":
            backend = backend or _jax_backend()
            if auto_physics(True, backend) == "native":
                return "native"
            if spec.gymnasium_id in MJX_REFUSAL:
                raise PhysicsError(
                    f"physics=auto on {backend} does not support env {task!r}: MJX cannot run it "
                    f"({MJX_REFUSAL[spec.gymnasium_id]}), and native MuJoCo would step on the host "
                    "(allowed: physics=native, to accept that)"
                )
            return "mjx"
        if physics == "native":
            return "native"
        if spec.gymnasium_id in MJX_REFUSAL:
            raise PhysicsError(f"physics=mjx does not support env {task!r}: {MJX_REFUSAL[spec.gymnasium_id]}")
        return "mjx"
    if physics == "native" and not spec.native:
        raise PhysicsError(
            f"physics=native does not support env {task!r}; supported envs: {', '.join(NATIVE_TASKS)}"
        )
    if spec.backend != "mjx":
        return spec.backend
    if physics == "auto":
        return auto_physics(spec.native, backend or _jax_backend())
    return physics


def _jax_backend() -> str:
    """JAX's default backend (``cpu``, ``gpu``, ``tpu``)."""
    import jax  # lazy: the config reads this module without JAX

    return jax.default_backend()
