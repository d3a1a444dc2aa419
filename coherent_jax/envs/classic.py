"""The classic exploration tasks in pure JAX: Gymnasium's ``MountainCarContinuous-v0`` and
``Pendulum-v1``, step for step.

Both follow Brax's ``Env`` interface, like `coherent_jax.envs.pointmass`, so they run
inside the jitted iteration under the same wrapper as every task (`coherent_jax.envs.vec_env`:
time limit, automatic resets, the agent's action clipped to [-1, 1]). The agent's action is
mapped onto Gymnasium's action space by `coherent_jax.envs.action_map.to_bounds` (centre + a *
half-width: [-1, 1] for the car, [-2, 2] for the pendulum), then clipped to the bounds as
Gymnasium's ``step`` clips it. The formulas are those of Gymnasium 1.4.0's
``continuous_mountain_car.py`` and ``pendulum.py`` at their default arguments, in float32
(Gymnasium's pendulum keeps its state in float64; `tests/test_classic_tasks.py` states the
tolerances).

MountainCarContinuous (2 obs: position, velocity; 1 act; 999-step episodes)::

    v' = clip(v + 0.0015 f - 0.0025 cos(3 x), -0.07, 0.07),  f = clip(a, -1, 1)
    x' = clip(x + v', -1.2, 0.6);  v' = 0 if x' = -1.2 and v' < 0
    terminated = x' >= 0.45 and v' >= 0;  r = 100 [terminated] - 0.1 a^2
    reset: x ~ U(-0.6, -0.4), v = 0

A 999-step episode's return is positive exactly when it reached the goal: reaching gives
at least 100 - 0.1 * 999 = 0.1, and without it every reward is <= 0.

Pendulum (3 obs: cos th, sin th, thdot; 1 act; 200-step episodes, no termination)::

    u = clip(a, -2, 2);  r = -(norm(th)^2 + 0.1 thdot^2 + 0.001 u^2),  norm(th) in [-pi, pi)
    thdot' = clip(thdot + (3 g / 2 l sin th + 3 / (m l^2) u) dt, -8, 8);  th' = th + thdot' dt
    g = 10, m = l = 1, dt = 0.05;  reset: th ~ U(-pi, pi), thdot ~ U(-1, 1)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State

from coherent_jax.envs.action_map import to_bounds


class _Classic(Env):
    """What both tasks share: a state of two numbers (``pipeline_state`` [2]), one action
    dimension mapped onto ``[-max_action, max_action]``, and no physics engine."""

    max_action: float = 1.0

    def action(self, action: jax.Array) -> jax.Array:
        """The agent's action in [-1, 1] -> the scalar Gymnasium's ``step`` receives; each task
        clips it to the bounds where Gymnasium's ``step`` does."""
        return to_bounds(action, -self.max_action, self.max_action)[0]

    @property
    def action_size(self) -> int:
        return 1

    @property
    def backend(self) -> str:
        return "jax"


class MountainCarContinuous(_Classic):
    """Gymnasium's ``MountainCarContinuous-v0``: an underpowered car must swing out of a valley
    to the flag on the right hill. The goal pays 100 once, every step costs 0.1 a^2, so a
    policy that does not find the goal learns to stand still."""

    min_position, max_position, max_speed = -1.2, 0.6, 0.07
    goal_position, goal_velocity, power = 0.45, 0.0, 0.0015

    def reset(self, rng: jax.Array) -> State:
        position = jax.random.uniform(rng, (), minval=-0.6, maxval=-0.4)
        phys = jnp.stack([position, jnp.zeros(())])
        return State(phys, phys, jnp.zeros(()), jnp.zeros(()), {}, {})

    def step(self, state: State, action: jax.Array) -> State:
        position, velocity = state.pipeline_state
        a = self.action(action)
        force = jnp.clip(a, -1.0, 1.0)
        velocity = velocity + force * self.power - 0.0025 * jnp.cos(3 * position)
        velocity = jnp.clip(velocity, -self.max_speed, self.max_speed)
        position = jnp.clip(position + velocity, self.min_position, self.max_position)
        velocity = jnp.where((position == self.min_position) & (velocity < 0), 0.0, velocity)
        goal = (position >= self.goal_position) & (velocity >= self.goal_velocity)
        reward = jnp.where(goal, 100.0, 0.0) - 0.1 * jnp.square(a)  # the action as given
        phys = jnp.stack([position, velocity])
        return state.replace(pipeline_state=phys, obs=phys, reward=reward, done=goal.astype(jnp.float32))

    @property
    def observation_size(self) -> int:
        return 2

    @property
    def dt(self) -> float:
        return 1.0  # no time unit: one step of the difference equations


class Pendulum(_Classic):
    """Gymnasium's ``Pendulum-v1``: swing a pendulum up from a random angle and hold it
    upright with a torque of at most 2; dense cost, no termination."""

    max_action = 2.0
    max_speed, g, m, length, time_step = 8.0, 10.0, 1.0, 1.0, 0.05

    def reset(self, rng: jax.Array) -> State:
        high = jnp.array([jnp.pi, 1.0])
        phys = jax.random.uniform(rng, (2,), minval=-high, maxval=high)
        return State(phys, self._obs(phys), jnp.zeros(()), jnp.zeros(()), {}, {})

    def step(self, state: State, action: jax.Array) -> State:
        th, thdot = state.pipeline_state
        u = jnp.clip(self.action(action), -self.max_action, self.max_action)
        norm_th = jnp.mod(th + jnp.pi, 2 * jnp.pi) - jnp.pi
        cost = jnp.square(norm_th) + 0.1 * jnp.square(thdot) + 0.001 * jnp.square(u)
        accel = 3 * self.g / (2 * self.length) * jnp.sin(th) + 3.0 / (self.m * self.length**2) * u
        thdot = jnp.clip(thdot + accel * self.time_step, -self.max_speed, self.max_speed)
        phys = jnp.stack([th + thdot * self.time_step, thdot])
        return state.replace(pipeline_state=phys, obs=self._obs(phys), reward=-cost)

    @staticmethod
    def _obs(phys: jax.Array) -> jax.Array:
        return jnp.stack([jnp.cos(phys[0]), jnp.sin(phys[0]), phys[1]])

    @property
    def observation_size(self) -> int:
        return 3

    @property
    def dt(self) -> float:
        return self.time_step


CLASSIC_TASKS = {"mountain_car_continuous": MountainCarContinuous, "pendulum": Pendulum}
