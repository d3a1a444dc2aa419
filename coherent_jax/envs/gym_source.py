"""Gymnasium environments as tasks: ``env=gym:ID``, ``env=gym:MODULE:ID``, or a
``gymnasium.Env`` of the user's own named ``env=MODULE:NAME`` / ``env=path/to/file.py:NAME``;
resolved and checked here, without JAX.

A Gymnasium env is stepped on the host (`coherent_jax.envs.host_gym`), so anything
Gymnasium can run trains here, within these limits, each refused in one line
(`TaskDefinitionError`, exit status 2 before any directory exists):

* a flat ``Box`` observation space (shape ``(obs_size,)``) and a ``Box`` action space
  (shape ``(action_size,)``) with finite bounds: the agent's action a in [-1, 1] is mapped
  onto them as centre + a * half-width (`coherent_jax.envs.action_map.to_bounds`), as for the
  built-in tasks; ``Dict``, ``Tuple``, ``Discrete`` and the other spaces are refused;
* ``reset(seed=0)`` and one ``step`` with a sample action must work, return a finite
  observation of the declared shape and a finite scalar reward (the env's own error is quoted).

What ``NAME`` may be follows the rule of the user's MJCF tasks: a ``gymnasium.Env`` subclass
(called with no arguments), or a function of no required arguments annotated to return one
(``-> gymnasium.Env``); nothing else is called. Time limits are the run's ``episode_length``
(default: the registered ``max_episode_steps``, else 1000), through Gymnasium's ``TimeLimit``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import inspect
import typing
from collections.abc import Callable
from typing import Any

import gymnasium
import mujoco
import numpy as np
from gymnasium import spaces
from gymnasium.wrappers import TimeLimit

from coherent_jax.envs.quiet import quiet_stdio
from coherent_jax.envs.spec import (
    TaskDefinitionError,
    first_line,
    gym_id_parts,
    import_module,
    refuse,
)

# What ``NAME`` may be when it is a Gymnasium env, said in refusals.
GYM_RULE = "a gymnasium.Env subclass, or a function of no arguments annotated '-> gymnasium.Env'"
# Episode length of an env that declares none.
DEFAULT_EPISODE_LENGTH = 1000


@dataclasses.dataclass(frozen=True)
class GymSource:
    """A checked Gymnasium env: how to build it and its sizes.

    Attributes:
      name: the ``env=`` value.
      build: () -> a fresh ``gymnasium.Env`` (no time limit added).
      observation_size: length of the flat observation.
      low, high: [action_size] finite action bounds, float32.
      episode_length: the default time limit in env steps.
      renders: whether the env was built with ``render_mode="rgb_array"`` (video works).
      dt: seconds per step (the env's ``dt``, else ``1 / metadata["render_fps"]``, else 0.05).
      action_dtype: the action space's dtype, what the env receives.
      own_limit: the ``max_episode_steps`` of a ``TimeLimit`` the built env already wears (a
        builder that returns ``gymnasium.make(ID)``), which no longer ``episode_length`` can
        outlast; None when it wears none (a registered id is built without its own).
    """

    name: str
    build: Callable[[], Any]
    observation_size: int
    low: np.ndarray
    high: np.ndarray
    episode_length: int
    renders: bool
    dt: float = 0.05
    action_dtype: Any = np.float32
    own_limit: int | None = None

    @property
    def action_size(self) -> int:
        return int(self.low.shape[0])

    def make(self, episode_length: int):
        """A fresh env whose episodes are truncated after ``episode_length`` steps."""
        return TimeLimit(self.build(), max_episode_steps=int(episode_length))


@contextlib.contextmanager
def quietly():
    """Builds and resets envs without their prints and MuJoCo's compiler warnings, which MuJoCo
    would otherwise append to ``MUJOCO_LOG.TXT`` in the working directory (Gymnasium's
    ``half_cheetah.xml`` uses a deprecated attribute)."""
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda message: None)
    try:
        with quiet_stdio(force=True):
            yield
    finally:
        mujoco.set_mju_user_warning(previous)


def gym_maker(obj: Any) -> str | None:
    """None if `obj` may be called to make a Gymnasium env (a ``gymnasium.Env`` subclass, or a
    Python function with no required parameters whose return annotation resolves to
    ``gymnasium.Env`` or a subclass); otherwise what it is, for the refusal. Nothing is called."""
    if inspect.isclass(obj):
        return None if issubclass(obj, gymnasium.Env) else f"the class {obj.__name__}"
    if not inspect.isfunction(obj):
        return f"of type {type(obj).__name__}"
    params = inspect.signature(obj).parameters.values()
    variadic = (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)
    required = [p.name for p in params if p.default is p.empty and p.kind not in variadic]
    if required:
        return f"a function of arguments ({', '.join(required)})"
    try:
        returns = typing.get_type_hints(obj).get("return")
    except Exception:  # an annotation that does not resolve
        returns = None
    if not (inspect.isclass(returns) and issubclass(returns, gymnasium.Env)):
        return "a function without the return annotation '-> gymnasium.Env'"
    return None


def _registered(name: str) -> tuple[Callable[[], Any], int]:
    """(builder, registered episode length) of ``gym:[MODULE:]ID``."""
    module, gym_id = gym_id_parts(name)
    if module:
        import_module(name, module)  # its registrations
    if gym_id not in gymnasium.registry:
        close = [k for k in gymnasium.registry if k.lower().startswith(gym_id.split("-")[0].lower()[:4])]
        hint = f" (close: {', '.join(sorted(close)[:6])})" if close else ""
        refuse(name, f"{gym_id!r} is not a registered Gymnasium id{hint}")
    length = gymnasium.spec(gym_id).max_episode_steps or DEFAULT_EPISODE_LENGTH
    # Without the registered TimeLimit: `GymSource.make` adds the run's own; rendering frames for
    # video=true where the env's class declares it can.
    spec = gymnasium.spec(gym_id)
    try:
        creator = gymnasium.envs.registration.load_env_creator(spec.entry_point)
        modes = (getattr(creator, "metadata", None) or {}).get("render_modes", ())
    except Exception:  # an entry point that does not load is refused when the env is built
        modes = ()
    render = {"render_mode": "rgb_array"} if "rgb_array" in modes else {}
    quiet = {
        "max_episode_steps": -1,
        "disable_env_checker": True,
    }  # -1: no TimeLimit (None: the registered one)
    build = functools.partial(gymnasium.make, gym_id, **quiet, **render)
    build.__name__ = f"gymnasium.make({gym_id!r})"
    return build, int(length)


def _checked_space(name: str, what: str, space: Any) -> None:
    if not isinstance(space, spaces.Box):
        refuse(name, f"{what} space is {type(space).__name__} (allowed: a flat Box)")
    if len(space.shape) != 1:
        refuse(name, f"{what} space has shape {space.shape} (allowed: a flat Box, shape (size,))")


def _try(name: str, what: str, fn: Callable[[], Any]) -> Any:
    try:
        with quietly():
            return fn()
    except TaskDefinitionError:
        raise
    except Exception as exc:
        refuse(name, f"{what} raised {first_line(exc)}")


def check_gym_env(name: str, build: Callable[[], Any], episode_length: int | None) -> GymSource:
    """Builds the env once and checks its spaces, ``reset`` and one ``step`` with a sample action;
    raises `TaskDefinitionError` in one line, quoting the env's own error. `episode_length` None:
    the env's ``spec.max_episode_steps``, else 1000."""
    what = getattr(build, "__name__", "building the env")
    env = _try(name, what if what.endswith(")") else f"{what}()", build)
    if not isinstance(env, gymnasium.Env):
        refuse(name, f"building it returned a {type(env).__name__}, not a gymnasium.Env")
    _checked_space(name, "observation", env.observation_space)
    _checked_space(name, "action", env.action_space)
    low, high = (np.asarray(b, np.float64) for b in (env.action_space.low, env.action_space.high))
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
        bounds = f"[{low.tolist()}, {high.tolist()}]"
        refuse(name, f"action bounds {bounds} are not finite (allowed: finite Box bounds)")
    obs_size = int(env.observation_space.shape[0])
    obs, _ = _try(name, "reset(seed=0)", lambda: env.reset(seed=0))
    _checked_obs(name, "reset", obs, obs_size)
    env.action_space.seed(0)
    out = _try(name, "step(sample action)", lambda: env.step(env.action_space.sample()))
    _checked_obs(name, "step", out[0], obs_size)
    if np.ndim(out[1]) != 0 or not np.isfinite(float(out[1])):
        refuse(name, f"step returned the reward {out[1]!r} (allowed: a finite scalar)")
    renders = getattr(env, "render_mode", None) == "rgb_array"
    fps = (getattr(env, "metadata", None) or {}).get("render_fps")
    dt = float(getattr(env.unwrapped, "dt", None) or (1.0 / fps if fps else 0.05))
    env.close()
    own_limit = worn_time_limit(env)
    if episode_length is None:
        episode_length = own_limit or DEFAULT_EPISODE_LENGTH
    return GymSource(
        name,
        build,
        obs_size,
        low.astype(np.float32),
        high.astype(np.float32),
        int(episode_length),
        renders,
        dt,
        np.dtype(env.action_space.dtype),
        own_limit,
    )


def worn_time_limit(env: Any) -> int | None:
    """The shortest ``max_episode_steps`` of the ``TimeLimit`` wrappers around `env`, or None."""
    limits = []
    while env is not None:
        if isinstance(env, TimeLimit):
            limits.append(int(env._max_episode_steps))
        env = getattr(env, "env", None)
    return min(limits) if limits else None


def _checked_obs(name: str, when: str, obs: Any, size: int) -> None:
    obs = np.asarray(obs)
    allowed = f"(allowed: finite numbers, shape ({size},))"
    if obs.shape != (size,) or not np.issubdtype(obs.dtype, np.number):
        refuse(name, f"{when} returned an observation {obs.dtype} of shape {obs.shape} {allowed}")
    if not np.all(np.isfinite(obs)):
        refuse(name, f"{when} returned an observation with {non_finite(obs)} {allowed}")


def non_finite(x: np.ndarray, most: int = 8) -> str:
    """Which entries of the flat `x` are not finite, by kind: ``NaN at entries [1, 3] and inf at
    entry [0]`` (at most `most` indices of each kind, then ``...``)."""
    parts = []
    for label, bad in (("NaN", np.isnan(x)), ("inf", np.isposinf(x)), ("-inf", np.isneginf(x))):
        at = np.flatnonzero(bad).tolist()
        if at:
            shown = ", ".join(map(str, at[:most])) + (", ..." if len(at) > most else "")
            parts.append(f"{label} at {'entry' if len(at) == 1 else 'entries'} [{shown}]")
    return " and ".join(parts)


def registered_gym_env(name: str) -> GymSource:
    """The checked env of ``gym:ID`` / ``gym:MODULE:ID``."""
    build, length = _registered(name)
    return check_gym_env(name, build, length)


def user_gym_env(name: str, obj: Any) -> GymSource:
    """The checked env of the user's ``MODULE:NAME`` whose attribute `obj` passed `gym_maker`: a
    class called with no arguments, or a factory; its episode length is its ``spec``'s, else 1000."""
    return check_gym_env(name, obj, None)


def render_problem(source: GymSource) -> str | None:
    """None if the env renders ``rgb_array`` frames (``video=true``), else why not (one line)."""
    if not source.renders:
        return "the env was not built with render_mode='rgb_array'"
    try:
        with quietly():
            env = source.build()
            env.reset(seed=0)
            frame = np.asarray(env.render())
            env.close()
    except Exception as exc:
        return f"its render() raised {first_line(exc)}"
    if frame.ndim != 3 or frame.shape[-1] != 3:
        return f"its render() returned shape {frame.shape}, not an RGB image"
    return None
