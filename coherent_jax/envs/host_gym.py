"""Gymnasium environments stepped on the host from inside the jitted iteration.

`GymPhysics` holds a pool of Python env copies on the host (`HostPool`) and reaches it
through a pure callback (`host_call`, XLA's buffers read and written in place), as native
MuJoCo is reached (`coherent_jax.envs.physics`), so the training iteration stays one
compiled function.

**Why a pure callback and a tick.** The pool has state (the envs), so its calls must run
once each, in program order. ``io_callback(ordered=True)`` would order them but cannot be
vmapped, and a sweep vmaps the whole iteration over its points. Instead every call takes
and returns a ``tick`` (the number of steps the pool has taken) that travels in the JAX
state: each call depends on the previous one's output, so XLA runs them in order and none
is dropped (its outputs are used). The host checks the tick of every call against its own
count and refuses one that is out of order or repeated, instead of silently stepping twice.

**Autoreset.** A step call steps every env; where the step ended the episode (terminated,
or truncated by Gymnasium's ``TimeLimit`` at the run's ``episode_length``) it keeps the
observation reached apart (``final_obs``, for bootstrapping on truncation) and resets the
env in the same call, so the next observation is the new episode's first: no step is lost
and none is counted twice. ``terminated`` and ``truncated`` stay apart.

**Seeds.** `reset` draws one 31-bit seed per env from the run's key and calls
``env.reset(seed=...)`` once; later episodes continue each env's own generator, so a run
is reproducible from its seed.

**Sweeps.** A sweep vmaps over its points: the callback receives [points, n, ...] rows and
one shared pool holds points * n envs, one row each (`HostPool` sizes itself at reset).

**Resume.** `HostPool.snapshot` / `HostPool.restore` give the pool's state as bytes (each env
pickled, its generator's state, and for MuJoCo envs the full ``MjData`` state), which the
checkpoint carries (`coherent_jax.run.checkpoint`), so a resumed run steps on bit for bit.
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from jax.experimental.buffer_callback import buffer_callback

from coherent_jax.envs.action_map import ActionMap
from coherent_jax.envs.gym_source import GymSource, quietly
from coherent_jax.envs.spec import first_line


@struct.dataclass
class GymState:
    """State of n host envs as JAX sees it (all [n, ...]).

    Attributes:
      obs: the observation the agent acts on now (after any reset), float32.
      reward: reward of the last step.
      done: 1.0 where the last step terminated (no bootstrap), else 0.0.
      truncated: the last step hit the time limit without terminating (bootstrap).
      final_obs: the observation the last step reached, before any reset.
      tick: steps the pool has taken; orders the callbacks (module docstring).
    """

    obs: jax.Array
    reward: jax.Array
    done: jax.Array
    truncated: jax.Array
    final_obs: jax.Array
    tick: jax.Array


class HostPool:
    """The host side: env copies, reset and stepped by `GymPhysics`'s callbacks."""

    def __init__(self, source: GymSource, episode_length: int):
        self.source = source
        self.episode_length = int(episode_length)
        self.envs: list[Any] = []
        self.tick = 0
        self._recording = False
        # Frames of env 0's first episode (``env.render()``) while a list: a video's source.
        self.frames: list[np.ndarray] | None = None
        self.max_frames = 0
        self.failure: str | None = None  # what an env raised (`_call`), for the run's one line

    def reset(self, seeds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fresh episodes, env i seeded with ``seeds[i]``; (obs [..., n, obs_size], tick [..., n])."""
        seeds = np.asarray(seeds)
        flat = seeds.reshape(-1)
        if len(self.envs) != flat.size:
            for env in self.envs:
                env.close()
            with quietly():
                self.envs = [self.source.make(self.episode_length) for _ in range(flat.size)]
        obs = np.stack(
            [
                self._call(i, "reset", env.reset, seed=int(s))[0]
                for i, (env, s) in enumerate(zip(self.envs, flat, strict=True))
            ]
        )
        self.tick = 0
        self._recording = self.frames is not None
        self._record()
        return obs.astype(np.float32).reshape(seeds.shape + obs.shape[1:]), np.zeros(seeds.shape, np.int32)

    def step(self, actions: np.ndarray, tick: np.ndarray) -> tuple[np.ndarray, ...]:
        """Steps env i with ``actions[i]``, resetting the envs whose episode ended; (obs, reward,
        terminated, truncated, final_obs, tick), each [..., n, ...]."""
        actions, tick = np.asarray(actions), np.asarray(tick)
        lead = tick.shape
        if not np.all(tick == self.tick) or tick.size != len(self.envs):
            raise RuntimeError(
                f"host env pool out of step: call for step {np.unique(tick).tolist()} of {tick.size} envs, "
                f"the pool is at step {self.tick} with {len(self.envs)} envs"
            )
        dtype = self.source.action_dtype
        flat = actions.reshape(len(self.envs), -1).astype(dtype)
        n = len(self.envs)
        obs = np.empty((n, self.source.observation_size), np.float32)
        final = np.empty_like(obs)
        reward = np.empty(n, np.float32)
        terminated, truncated = np.zeros(n, bool), np.zeros(n, bool)
        for i, env in enumerate(self.envs):
            o, r, term, trunc, _ = self._call(i, "step", env.step, flat[i])
            final[i], reward[i], terminated[i], truncated[i] = o, r, term, trunc and not term
            if i == 0:
                self._record()
                self._recording = self._recording and not (term or trunc)
            obs[i] = self._call(i, "reset", env.reset)[0] if term or trunc else o
        self.tick += 1

        def shaped(x):
            return x.reshape(lead + x.shape[1:])

        return (
            shaped(obs),
            shaped(reward),
            shaped(terminated.astype(np.float32)),
            shaped(truncated),
            shaped(final),
            np.full(lead, self.tick, np.int32),
        )

    def _call(self, i: int, what: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """``fn(*args)`` of env `i`; an error it raises is kept as ``failure`` (one line: the
        env, the call and the error) for the run to report, since XLA's callback error that
        carries it out of the jit wraps it in a long traceback."""
        try:
            return fn(*args, **kwargs)
        except Exception as exc:
            self.failure = (
                f"{self.source.name} raised in {what}() of env {i} at step {self.tick + 1}: {first_line(exc)}"
            )
            raise

    def _record(self) -> None:
        if self._recording and len(self.frames) < self.max_frames:
            self.frames.append(np.asarray(self.envs[0].render()))

    def snapshot(self) -> bytes:
        """The pool's state: every env pickled with its generator and MuJoCo state."""
        return pickle.dumps({"tick": self.tick, "envs": [_env_state(env) for env in self.envs]})

    def restore(self, blob: bytes) -> None:
        """Puts the pool back where `snapshot` was taken."""
        for env in self.envs:
            env.close()
        with quietly():  # unpickling a MuJoCo env builds its model again
            state = pickle.loads(blob)
            self.envs = [_env_from(s) for s in state["envs"]]
        self.tick = int(state["tick"])


def _env_state(env: Any) -> dict[str, Any]:
    """A picklable record of `env`: the env itself, and what pickling an env may drop (Gymnasium's
    MuJoCo envs pickle as their constructor arguments): its generator and MuJoCo state."""
    inner = env.unwrapped
    record = {"env": env, "np_random": getattr(inner, "_np_random", None)}
    data, model = getattr(inner, "data", None), getattr(inner, "model", None)
    if data is not None and model is not None and hasattr(data, "qpos"):
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        state = np.empty(mujoco.mj_stateSize(model, spec))
        mujoco.mj_getState(model, data, state, spec)
        warm = np.array(data.qacc_warmstart)
        record["mujoco"] = (state, warm)
    return record


def _env_from(record: dict[str, Any]) -> Any:
    env = record["env"]
    inner = env.unwrapped
    if record["np_random"] is not None:
        inner._np_random = record["np_random"]
    if "mujoco" in record:
        state, warm = record["mujoco"]
        mujoco.mj_setState(inner.model, inner.data, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        mujoco.mj_forward(inner.model, inner.data)
        inner.data.qacc_warmstart[:] = warm
    return env


def host_call(fn: Callable[..., tuple[np.ndarray, ...]], shapes: tuple, *args: jax.Array) -> tuple:
    """``fn(*args)`` on the host as NumPy arrays, from inside the jit: a pure callback whose arguments
    and results are XLA's own buffers read and written in place (``buffer_callback``), not copied
    into JAX arrays first as ``jax.pure_callback`` copies them (``device_put``, most of a call's
    cost on CPU: ``python -m benchmarks gym``). Under vmap ``fn`` gets the batch's leading
    axes."""

    def callback(ctx, out, *buffers):
        results = fn(*(np.asarray(b) for b in buffers))
        for o, r in zip(out, results, strict=True):
            np.asarray(o)[...] = r

    return tuple(buffer_callback(callback, shapes, vmap_method="broadcast_all")(*args))


def env_seeds(keys: jax.Array) -> jax.Array:
    """The ``env.reset(seed=...)`` of each env, [n] int32 in [0, 2^31 - 1), from its key [n]."""
    return jax.vmap(lambda k: jax.random.randint(k, (), 0, 2**31 - 1))(keys)


class GymPhysics:
    """Batched reset and step of one Gymnasium env's host pool, callable under jit; both take the
    whole batch (the pool steps every env in one call). Interface of the other engines: ``reset``
    (keys [n]) and ``step`` (state, action [n, action_size] in [-1, 1]), sizes and ``dt``."""

    state_type = GymState

    def __init__(self, source: GymSource, episode_length: int):
        self.source = source
        self.pool = HostPool(source, episode_length)
        self.observation_size = source.observation_size
        self.action_size = source.action_size
        self.dt = source.dt
        # The map onto the env's Box (Gymnasium's eq. A); a shipped policy reads it from here.
        self.action_map = ActionMap.of_box(source)

    def reset(self, keys: jax.Array) -> GymState:
        seeds = env_seeds(keys)
        n = keys.shape[0]
        shapes = (
            jax.ShapeDtypeStruct((n, self.observation_size), jnp.float32),
            jax.ShapeDtypeStruct((n,), jnp.int32),
        )
        obs, tick = host_call(self.pool.reset, shapes, seeds)
        zeros = jnp.zeros((n,), jnp.float32)
        return GymState(obs, zeros, zeros, jnp.zeros((n,), bool), obs, tick)

    def step(self, state: GymState, action: jax.Array) -> GymState:
        n = action.shape[0]
        env_action = self.action_map.unclipped(action)
        shapes = (
            jax.ShapeDtypeStruct((n, self.observation_size), jnp.float32),
            jax.ShapeDtypeStruct((n,), jnp.float32),
            jax.ShapeDtypeStruct((n,), jnp.float32),
            jax.ShapeDtypeStruct((n,), jnp.bool_),
            jax.ShapeDtypeStruct((n, self.observation_size), jnp.float32),
            jax.ShapeDtypeStruct((n,), jnp.int32),
        )
        out = host_call(self.pool.step, shapes, env_action, state.tick)
        return GymState(*out)


def host_pool(env: Any) -> HostPool | None:
    """The host pool of a `coherent_jax.envs.vec_env.VecEnv` running a Gymnasium env, else None."""
    return getattr(getattr(env, "env", None), "pool", None)
