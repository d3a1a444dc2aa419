"""JAX environments with Brax's interface of the user's own, named ``env=MODULE:NAME`` or
``env=path/to/file.py:NAME``: Brax's environments, MuJoCo Playground's, and those of
research code written against the same interface.

Brax's interface is ``reset(key) -> state`` and ``step(state, action) -> state``, where
a state carries ``obs``, ``reward`` and ``done``, and ``action_size``, the length of the
action vector in [-1, 1]. ``NAME`` is one of:

* an instance of ``brax.envs.Env`` or of Playground's ``MjxEnv`` (or of a subclass);
* such a class, built with no arguments;
* a function of no required arguments annotated to return one
  (``def make() -> MjxEnv: ...``).

What ``NAME`` is is read before anything is called (the classes are recognised by name
along their method resolution order, so neither Brax nor Playground is imported to ask),
so no other callable is ever run. `load_jax_env` builds the env once per process and
checks, by tracing ``reset`` and ``step`` vmapped over two envs as training runs them
(`jax.eval_shape`, nothing compiled), that the observation is one flat float vector (a
dict of observations is refused), the reward and ``done`` scalars per env, and the
action size an integer >= 1. A problem raises `TaskDefinitionError` in one line.

The env runs inside the jitted iteration like the built-in Brax tasks (`VecEnv` vmaps
``reset`` and ``step`` and adds the time limit and the auto-reset), on whatever backend
the env itself uses: ``physics=auto`` only. The time limit is the env's own
``episode_length`` where its config has one (Playground's), else 1000 steps. Video
renders the env's MuJoCo model where it exposes one (``mj_model``, or Brax's
``sys.mj_model``) and its states carry the positions (``data.qpos`` or
``pipeline_state.q``).
"""

from __future__ import annotations

import inspect
import typing
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from coherent_jax.envs.spec import TaskSpec, first_line, refuse

# The registry's backend of this kind of task (`coherent_jax.envs.registry.resolve_physics`).
JAX_ENV_BACKEND = "jax-env"
# The classes that define Brax's interface, by (module, qualified name).
_INTERFACE_CLASSES = frozenset({("brax.envs.base", "Env"), ("mujoco_playground._src.mjx_env", "MjxEnv")})
# What ``NAME`` may be, said in every refusal of another kind of attribute.
JAX_ENV_RULE = (
    "a brax.envs.Env or mujoco_playground MjxEnv instance, a subclass of one, or a function "
    "of no arguments annotated to return one"
)
DEFAULT_EPISODE_LENGTH = 1000


def _is_interface_class(cls: Any) -> bool:
    return inspect.isclass(cls) and any(
        (c.__module__, c.__qualname__) in _INTERFACE_CLASSES for c in inspect.getmro(cls)
    )


def _factory_returns_env(obj: Any) -> bool:
    """Whether `obj` is a Python function of no required arguments whose return annotation
    resolves to a class with Brax's interface (nothing is called)."""
    if not inspect.isfunction(obj):
        return False
    params = inspect.signature(obj).parameters.values()
    if any(p.default is p.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD) for p in params):
        return False
    try:
        returns = typing.get_type_hints(obj).get("return")
    except Exception:  # an annotation that does not resolve: not declared to make an env
        return False
    return _is_interface_class(returns)


def is_brax_env(obj: Any) -> bool:
    """Whether the attribute `obj` of ``MODULE:NAME`` names a JAX env with Brax's interface:
    an instance of ``brax.envs.Env`` or Playground's ``MjxEnv``, such a class, or a function
    declared to return one. Nothing is called or imported."""
    return _is_interface_class(obj) or _is_interface_class(type(obj)) or _factory_returns_env(obj)


class LoadedJaxEnv(NamedTuple):
    """A checked JAX env: its registry entry and the env `VecEnv` steps."""

    spec: TaskSpec
    env: BraxInterfaceEnv


class BraxInterfaceEnv:
    """The user's env as `VecEnv` steps it: its own ``reset`` and ``step`` unchanged, and its
    step duration ``dt`` (1.0 where the env has none: a video then plays one step a second).

    Attributes:
      env: the user's env.
      action_size: the length of the action vector.
      dt: env step duration in seconds.
    """

    def __init__(self, env: Any):
        self.env = env
        self.action_size = int(env.action_size)
        self.dt = float(getattr(env, "dt", 1.0))

    def reset(self, key: jax.Array) -> Any:
        return self.env.reset(key)

    def step(self, state: Any, action: jax.Array) -> Any:
        return self.env.step(state, action)

    @property
    def mj_model(self) -> Any:
        """The env's MuJoCo model (Playground's ``mj_model``, Brax's ``sys.mj_model``), or None."""
        model = getattr(self.env, "mj_model", None)
        if model is None:
            model = getattr(getattr(self.env, "sys", None), "mj_model", None)
        return model

    @staticmethod
    def qpos(state: Any) -> jax.Array:
        """[n, nq] generalized positions of a batch of the env's states, for video: Playground's
        ``data.qpos`` or Brax's ``pipeline_state.q``."""
        if hasattr(state, "data"):
            return state.data.qpos
        physics = state.pipeline_state
        return physics.qpos if hasattr(physics, "qpos") else physics.q


def _built(name: str, obj: Any) -> Any:
    """The env `obj` names: itself, or what its class or factory builds."""
    if not (inspect.isclass(obj) or inspect.isfunction(obj)):
        return obj
    what = f"{getattr(obj, '__name__', 'NAME')}()"
    try:
        env = obj()
    except Exception as exc:
        refuse(name, f"{what} raised {first_line(exc)}")
    if not _is_interface_class(type(env)):
        refuse(name, f"{what} returned a {type(env).__name__}, not {JAX_ENV_RULE}")
    return env


def _checked_trace(name: str, env: Any) -> int:
    """The observation size, from the states after a reset and after a zero-action step of two
    envs, traced (shapes only) with ``vmap`` as `VecEnv` runs them, and checked."""
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    hint = ""
    if _is_interface_class(type(env)) and hasattr(env, "mjx_model"):
        hint = " (Playground's envs vmap with config_overrides={'impl': 'jax'})"
    try:
        first = jax.eval_shape(jax.vmap(env.reset), keys)
    except Exception as exc:
        refuse(name, f"reset fails under jax.vmap ({first_line(exc)}){hint}")
    obs_size = _checked_state(name, "after a reset", first)
    try:
        actions = jnp.zeros((2, int(env.action_size)), jnp.float32)
        after = jax.eval_shape(jax.vmap(env.step), first, actions)
    except Exception as exc:
        refuse(name, f"step fails under jax.vmap ({first_line(exc)}){hint}")
    if _checked_state(name, "after a step", after) != obs_size:
        refuse(name, f"the observation changes size from {obs_size} after a step")
    return obs_size


def _checked_state(name: str, when: str, state: Any) -> int:
    """The observation size of a traced state [2, ...]; refuses dict or non-flat observations
    and non-scalar rewards or dones."""
    for field in ("obs", "reward", "done"):
        if not hasattr(state, field):
            refuse(name, f"the state {when} has no '{field}' (Brax's interface: obs, reward, done)")
    obs = state.obs
    if isinstance(obs, typing.Mapping):
        refuse(
            name,
            f"observations are a dict ({', '.join(map(str, obs))}) {when}; "
            "allowed: one flat vector of floats (flatten it in the env)",
        )
    if not hasattr(obs, "shape") or len(obs.shape) != 2 or obs.shape[1] < 1:
        shape = tuple(obs.shape[1:]) if hasattr(obs, "shape") else type(obs).__name__
        refuse(name, f"the observation {when} has shape {shape} per env; allowed: a vector [obs_size]")
    if not jnp.issubdtype(obs.dtype, jnp.floating):
        refuse(name, f"the observation {when} is {obs.dtype}; allowed: floats")
    for field in ("reward", "done"):
        value = getattr(state, field)
        if getattr(value, "shape", None) != (2,):
            shape = tuple(value.shape[1:]) if hasattr(value, "shape") else type(value).__name__
            refuse(name, f"{field} {when} has shape {shape} per env; allowed: a scalar")
    return int(obs.shape[1])


def _episode_length(env: Any) -> int:
    """The env's own time limit (Playground's ``config.episode_length``), else the default."""
    config = getattr(env, "_config", None)
    length = getattr(config, "episode_length", None) if config is not None else None
    if isinstance(length, int) and not isinstance(length, bool) and length >= 1:
        return length
    return DEFAULT_EPISODE_LENGTH


# The envs built in this process, by task name (`load_jax_env` fills it).
_LOADED: dict[str, LoadedJaxEnv] = {}


def load_jax_env(name: str, obj: Any) -> LoadedJaxEnv:
    """The env of task ``name``, whose attribute is `obj` (`is_brax_env`), built and checked
    (see the module's docstring) once per process. Raises `TaskDefinitionError`."""
    if name in _LOADED:
        return _LOADED[name]
    env = _built(name, obj)
    try:
        action_size = env.action_size
    except Exception as exc:
        refuse(name, f"action_size raised {first_line(exc)}")
    if isinstance(action_size, bool) or not isinstance(action_size, int) or action_size < 1:
        refuse(name, f"action_size is {action_size!r}; allowed: an integer >= 1")
    obs_size = _checked_trace(name, env)
    spec = TaskSpec(
        "",
        None,
        episode_length=_episode_length(env),
        description=f"a JAX env of your own, {type(env).__name__} ({obs_size} obs, {action_size} act)",
        backend=JAX_ENV_BACKEND,
    )
    _LOADED[name] = LoadedJaxEnv(spec, BraxInterfaceEnv(env))
    return _LOADED[name]


def jax_env(name: str) -> BraxInterfaceEnv:
    """The env of task ``name``, loaded by the registry's check of it
    (`coherent_jax.envs.registry.check_task`, which calls it first)."""
    if name not in _LOADED:
        refuse(name, "not loaded as a JAX environment (check_task loads it)")
    return _LOADED[name].env
