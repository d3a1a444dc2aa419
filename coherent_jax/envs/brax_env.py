"""Environments with Brax's interface: a registry task's, made by name (`make_brax_env`), and
this package's own, in pure JAX (``pointmass`` and Gymnasium's classic exploration tasks).

`make_brax_env` builds the raw (unwrapped, unbatched) env of every task that runs inside the
jitted iteration as Brax's envs run (``reset(key)``, ``step(state, action)``, states with
``obs``, ``reward``, ``done``): Brax's own (``brax-*``), MuJoCo Playground's (``dmc-*``), the
user's JAX env (`coherent_jax.envs.jax_env`) and the tasks defined below, which subclass
Brax's ``Env``; `coherent_jax.envs.vec_env` vmaps them and adds the time limit and the
auto-reset. `env_sizes` reads their sizes without running them.

**pointmass**: a point mass that must reach a target, an analytic task. No physics engine:
its whole training iteration compiles in 7-15 s on two shared cores (docs/tasks.md), so
tests of the training machinery (collection, losses, strategies, the CLI) use it, while
learning tests use the MuJoCo tasks::

    p_{t+1} = p_t + dt v_{t+1},   v_{t+1} = damping v_t + dt a_t,   a in [-1, 1]^2
    r_t     = -|p_{t+1} - g| - 0.01 |a_t|^2

**The classic exploration tasks**: Gymnasium's ``MountainCarContinuous-v0`` and
``Pendulum-v1``, step for step. The agent's action is mapped onto Gymnasium's action space
by `coherent_jax.envs.action_map.to_bounds` (centre + a * half-width: [-1, 1] for the car,
[-2, 2] for the pendulum), after `coherent_jax.envs.vec_env`'s clip to [-1, 1], then clipped
to the bounds as Gymnasium's ``step`` clips it. The formulas are those of Gymnasium 1.4.0's
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

import warnings
from typing import Any

import jax
import jax.numpy as jnp

from coherent_jax.envs.action_map import to_bounds
from coherent_jax.envs.jax_env import JAX_ENV_BACKEND, jax_env
from coherent_jax.envs.quiet import quiet_imports, quiet_stdio
from coherent_jax.envs.registry import SHORT_NAMES, UnknownTaskError, check_task

quiet_imports()  # MJX before Brax imports it: muted, without its Warp engine
from brax.envs.base import Env, State  # noqa: E402


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


# --- pointmass: the analytic test task
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


# --- Gymnasium's classic exploration tasks, step for step
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
