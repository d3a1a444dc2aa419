"""A point mass that must reach a target: an analytic task in pure JAX.

No physics engine: its whole training iteration compiles in 7-15 s on two shared
cores (docs/tasks.md), so tests of the training machinery (collection, losses,
strategies, the CLI) use it, while learning tests use the MuJoCo tasks. It follows
Brax's ``Env`` interface, so the same wrappers apply.

    p_{t+1} = p_t + dt v_{t+1},   v_{t+1} = damping v_t + dt a_t,   a in [-1, 1]^2
    r_t     = -|p_{t+1} - g| - 0.01 |a_t|^2
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State


class PointMass(Env):
    """2D point mass with a random goal; observation [p, v, g - p] (6), action 2."""

    def __init__(self, dt: float = 0.1, damping: float = 0.9):
        self._dt = dt
        self._damping = damping

    def reset(self, rng: jax.Array) -> State:
        k_pos, k_goal = jax.random.split(rng)
        pos = jax.random.uniform(k_pos, (2,), minval=-1.0, maxval=1.0)
        goal = jax.random.uniform(k_goal, (2,), minval=-1.0, maxval=1.0)
        phys = {"pos": pos, "vel": jnp.zeros(2), "goal": goal}
        return State(phys, self._obs(phys), jnp.zeros(()), jnp.zeros(()), {}, {})

    def step(self, state: State, action: jax.Array) -> State:
        phys = state.pipeline_state
        vel = self._damping * phys["vel"] + self._dt * action
        pos = phys["pos"] + self._dt * vel
        phys = {"pos": pos, "vel": vel, "goal": phys["goal"]}
        reward = -jnp.linalg.norm(pos - phys["goal"]) - 0.01 * jnp.sum(jnp.square(action))
        return state.replace(pipeline_state=phys, obs=self._obs(phys), reward=reward)

    @staticmethod
    def _obs(phys) -> jax.Array:
        return jnp.concatenate([phys["pos"], phys["vel"], phys["goal"] - phys["pos"]])

    @property
    def observation_size(self) -> int:
        return 6

    @property
    def action_size(self) -> int:
        return 2

    @property
    def backend(self) -> str:
        return "jax"

    @property
    def dt(self) -> float:
        return self._dt
