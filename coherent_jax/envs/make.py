"""The environments of the registry's tasks with Brax's interface (`make_brax_env`), and their
sizes (`env_sizes`); `coherent_jax.envs.vec_env` batches them."""

from __future__ import annotations

import warnings
from typing import Any

import jax

from coherent_jax.envs.classic import CLASSIC_TASKS
from coherent_jax.envs.jax_env import JAX_ENV_BACKEND, jax_env
from coherent_jax.envs.pointmass import PointMass
from coherent_jax.envs.quiet import quiet_stdio
from coherent_jax.envs.registry import SHORT_NAMES, UnknownTaskError, check_task


def make_brax_env(name: str, **kwargs: Any):
    """Builds the raw (unwrapped, unbatched) environment of task `name` with Brax's interface
    (``reset(key)``, ``step(state, action)``, states with ``obs``, ``reward``, ``done``): a
    ``brax-*`` task, a ``dmc-*`` task (Playground's env) or ``pointmass``; Gymnasium's
    tasks are not Brax environments."""
    spec = check_task(name)
    if spec.backend == JAX_ENV_BACKEND:  # a JAX env of the user's, loaded by check_task
        return jax_env(name)
    if spec.playground_id:
        return make_playground_env(spec.playground_id, **kwargs)
    if spec.backend == "jax":  # this package's own pure-JAX tasks
        return {"pointmass": PointMass, **CLASSIC_TASKS}[spec.brax_name](**kwargs)
    if spec.gymnasium_id:
        short = next(s for s, g in SHORT_NAMES.items() if g == spec.gymnasium_id)
        raise UnknownTaskError(
            f"env {name!r} is Gymnasium's {spec.gymnasium_id} on native MuJoCo, not a Brax env; "
            f"Brax's re-creation is 'brax-{short}'"
        )
    # Brax prints a warning for its optional Warp backend on import; it is noise here.
    with quiet_stdio():
        from brax import envs as brax_envs  # lazy: slow; brax-* tasks only

    with warnings.catch_warnings():
        # Brax warns that its own pipelines are unmaintained; we use the MJX one.
        warnings.filterwarnings("ignore", message="Brax System, piplines")
        with quiet_stdio(force=True):  # MuJoCo's compiler prints deprecation notes
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
        with quiet_stdio(force=True):  # Warp prints its kernel-cache lines on import
            from mujoco_playground import registry as playground  # lazy: slow; dmc-* tasks only
    except ImportError as err:  # pragma: no cover - a dependency of the package
        raise UnknownTaskError(
            f"the DeepMind Control tasks need MuJoCo Playground (pip install playground): {err}"
        ) from None
    with quiet_stdio(force=True):
        return playground.load(playground_id, config_overrides={"impl": "jax", **config_overrides})


def env_sizes(env) -> tuple[int, int]:
    """(observation size, action size) of a Brax env without running it.

    Brax's ``observation_size`` property runs an eager reset, hundreds of small XLA
    compilations (about 20 s on this CPU); ``jax.eval_shape`` only traces it.
    """
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    return int(state.obs.shape[-1]), int(env.action_size)
