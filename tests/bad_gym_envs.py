"""Gymnasium envs of a user's that coherent_jax refuses, and three it takes (tests/test_gym_envs.py,
tests/test_gym_policy.py)."""

import os

import gymnasium
import numpy as np
from gymnasium import spaces


class _Base(gymnasium.Env):
    observation_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, np.float32), {}

    def step(self, action):
        return np.zeros(2, np.float32), 0.0, False, False, {}


class DictObs(_Base):
    observation_space = spaces.Dict({"x": spaces.Box(-1.0, 1.0, (2,), np.float32)})


class TupleAct(_Base):
    action_space = spaces.Tuple((spaces.Box(-1.0, 1.0, (1,), np.float32),))


class ImageObs(_Base):
    observation_space = spaces.Box(0, 255, (4, 4), np.uint8)


class Unbounded(_Base):
    action_space = spaces.Box(-np.inf, np.inf, (1,), np.float32)


class ResetFails(_Base):
    def reset(self, *, seed=None, options=None):
        raise ValueError("the reset is broken")


class StepFails(_Base):
    def step(self, action):
        raise KeyError("no such joint")


def not_annotated():
    return _Base()


class Good(_Base):
    """A valid env, registered on import (``env=gym:bad_gym_envs:BadGymEnvsGood-v0``)."""


class Skewed(_Base):
    """A valid env whose Box is neither [-1, 1] nor symmetric (tests/test_gym_policy.py)."""

    action_space = spaces.Box(np.array([-3.0, 0.0], np.float32), np.array([1.0, 0.5], np.float32))


def good_factory() -> gymnasium.Env:
    return Good()


gymnasium.register("BadGymEnvsGood-v0", entry_point=f"{__name__}:Good", max_episode_steps=30)


def limited_factory() -> gymnasium.Env:
    """Its env wears the registered TimeLimit of 30 steps: no longer episode_length can outlast it."""
    return gymnasium.make("BadGymEnvsGood-v0", disable_env_checker=True)


class NanReset(_Base):
    """Its reset's observation holds a NaN (refused, naming the entry)."""

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.array([0.0, np.nan], np.float32), {}


class InfStep(_Base):
    """Its step's observation holds -inf and NaN (refused, naming both)."""

    def step(self, action):
        return np.array([-np.inf, np.nan], np.float32), 0.0, False, False, {}


class BreaksLater(_Base):
    """Its ``step`` raises from the N-th call of the process on (all its instances together)
    while the environment variable BAD_GYM_BREAK_AT is N: an env that fails mid-run, and is
    fixed by unsetting it."""

    calls = 0

    def step(self, action):
        BreaksLater.calls += 1
        at = os.environ.get("BAD_GYM_BREAK_AT")
        if at and BreaksLater.calls >= int(at):
            raise RuntimeError(f"the joint broke at call {BreaksLater.calls}")
        return super().step(action)
