"""The overlap suite's two ways of stepping the envs as K groups inside the scanned step.

* `grouped_unroll` (**groups**): K independent chains (policy -> physics -> auto-reset)
  per step, one ``jax.pure_callback`` per group. Whether they overlap is up to XLA's CPU
  runtime, which runs a host callback inline on the thread that reaches it.
* `pipelined_unroll` (**pipeline**): the K groups in a ring whose host physics runs on a
  worker thread between two callbacks (`TwoPhaseHost`): ``start`` hands a group's state
  rows and controls to the worker and returns a ticket at once; ``finish`` waits for the
  worker's result. Group g's ``start`` comes before group g-1's ``finish`` and group g's
  policy before its ``start`` (data dependences), so the worker steps one group while XLA
  computes the next group's policy and the previous group's observation, reward and
  auto-reset. Group K-1's last physics step of a segment runs across the scan's step
  boundary, under group 0's next policy.

Both take and return the state of all n envs (group g holds envs g n/K ... (g+1) n/K - 1,
the strategy's carry cut the same way) and the [T, n] transitions in the envs' order. Each
group acts with its own key (``fold_in(step key, g)``): the same work as one group, not
the same draws. Native physics only (`coherent_jax.envs.physics.NativePhysics`).
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from coherent_jax.agents.rollout import ActFn, Transition
from coherent_jax.envs.mujoco_task import control
from coherent_jax.envs.physics import NativePhysics
from coherent_jax.envs.vec_env import EnvState, VecEnv
from coherent_jax.exploration.base import ActOutput


class HostClock:
    """Seconds spent inside native MuJoCo's host step (`wrap`), summed until read and reset."""

    def __init__(self):
        self.seconds = 0.0
        self._lock = threading.Lock()

    def wrap(self, fn: Callable) -> Callable:
        def timed(*args):
            t0 = time.perf_counter()
            try:
                return fn(*args)
            finally:
                with self._lock:
                    self.seconds += time.perf_counter() - t0

        return timed

    def take(self) -> float:
        """The seconds summed since the last call."""
        with self._lock:
            seconds, self.seconds = self.seconds, 0.0
        return seconds


def timed_env(vec: VecEnv, clock: HostClock) -> VecEnv:
    """``vec`` with its native host step timed by ``clock`` (before anything traces it)."""
    if not isinstance(vec.env, NativePhysics):
        raise ValueError(f"the overlap probe needs native physics; {vec.task} runs on {vec.physics}")
    vec.env.host.step = clock.wrap(vec.env.host.step)
    return vec


def split_groups(tree: Any, k: int) -> list[Any]:
    """``tree``'s leaves (leading axis n) cut into k consecutive groups of n / k."""
    return [jax.tree.map(lambda x, g=g: jnp.split(x, k)[g], tree) for g in range(k)]


def join_groups(trees: Sequence[Any]) -> Any:
    """The inverse of `split_groups`: the groups' leaves concatenated on the leading axis."""
    return jax.tree.map(lambda *xs: jnp.concatenate(xs), *trees)


def split_env_state(state: EnvState, k: int) -> list[EnvState]:
    """Per-group env states; the PRNG key (no env axis) is split, one per group."""
    parts = split_groups(state.replace(key=jnp.zeros((state.obs.shape[0],))), k)
    keys = jax.random.split(state.key, k)
    return [p.replace(key=keys[g]) for g, p in enumerate(parts)]


def join_env_state(states: Sequence[EnvState]) -> EnvState:
    joined = join_groups([s.replace(key=jnp.zeros((s.obs.shape[0],))) for s in states])
    return joined.replace(key=states[0].key)


def _transition(state: EnvState, out: ActOutput, outcome) -> Transition:
    return Transition(
        obs=state.obs,
        first=state.first,
        action=out.action,
        log_prob=out.log_prob,
        reward=outcome.reward,
        terminated=outcome.terminated,
        truncated=outcome.truncated,
        final_obs=outcome.final_obs,
        episode_return=outcome.episode_return,
        extras=out.extras,
    )


def grouped_unroll(
    groups: Sequence[VecEnv], act: ActFn, env_state: EnvState, carry: Any, key: jax.Array, length: int
) -> tuple[EnvState, Any, Transition]:
    """`coherent_jax.agents.rollout.unroll` with the envs as ``len(groups)`` independent chains per step."""
    k = len(groups)

    def step(state, step_key):
        env_states, carries = state
        new_states, new_carries, transitions = [], [], []
        for g, env in enumerate(groups):
            s = env_states[g]
            out = act(jax.random.fold_in(step_key, g), carries[g], s.obs, s.first)
            nxt, outcome = env.step(s, out.action)
            new_states.append(nxt)
            new_carries.append(out.carry)
            transitions.append(_transition(s, out, outcome))
        return (tuple(new_states), tuple(new_carries)), join_groups(transitions)

    init = (tuple(split_env_state(env_state, k)), tuple(split_groups(carry, k)))
    (states, carries), data = jax.lax.scan(step, init, jax.random.split(key, length))
    return join_env_state(states), join_groups(carries), data


class TwoPhaseHost:
    """Native physics on a one-thread worker, reached by two callbacks: `start` and `finish`."""

    def __init__(self):
        self._worker = ThreadPoolExecutor(1)
        self._jobs: dict[int, Future] = {}
        self._tickets = itertools.count(1)
        self._lock = threading.Lock()

    def start(self, host_step: Callable, rows, ctrl, go) -> np.ndarray:
        """Hands ``host_step(rows, ctrl)`` to the worker (if ``go``); returns its ticket (0: none)."""
        if not bool(go):
            return np.zeros((), np.int32)
        rows, ctrl = np.array(rows), np.array(ctrl)  # copies: the callback's buffers are XLA's
        with self._lock:
            ticket = next(self._tickets)
            self._jobs[ticket] = self._worker.submit(host_step, rows, ctrl)
        return np.asarray(ticket, np.int32)

    def finish(self, ticket, *after) -> tuple[np.ndarray, ...]:
        """Waits for the job of ``ticket`` and returns its result (``after``: order only)."""
        del after
        with self._lock:
            job = self._jobs.pop(int(ticket))
        return job.result()

    def deferred(self, vec: VecEnv) -> Callable:
        """Makes ``vec``'s physics step read a started job: returns ``step(state, action, ticket,
        after) -> (state, outcome)``, `VecEnv.step` with ``finish(ticket, after)`` for its physics."""
        phys: NativePhysics = vec.env
        slot: dict[str, jax.Array] = {}

        def advance(rows, ctrl):
            del ctrl
            shapes = phys._shapes(rows.shape[0])
            rows, *arrays = jax.pure_callback(self.finish, shapes, slot["ticket"], slot["after"])
            return rows, phys._kinematics(arrays)

        phys._advance = advance  # the instance's own: `TaskPhysics.step` calls it

        def step(state: EnvState, action: jax.Array, ticket: jax.Array, after: jax.Array):
            slot.update(ticket=ticket, after=after)
            return vec.step(state, action)

        return step

    def start_step(self, vec: VecEnv, state: EnvState, action: jax.Array, go: jax.Array) -> jax.Array:
        """Starts ``vec``'s physics step from ``state`` with ``action``, clipped and mapped as
        `VecEnv.step` does; returns the ticket."""
        phys: NativePhysics = vec.env
        ctrl = control(phys.spec, jnp.clip(action, -1.0, 1.0), phys.ctrl_range)
        ticket = jax.ShapeDtypeStruct((), jnp.int32)

        def start(rows, ctrl, go):
            return self.start(phys.host.step, rows, ctrl, go)

        return jax.pure_callback(start, ticket, state.physics.engine, ctrl, go)


def pipelined_unroll(
    groups: Sequence[VecEnv],
    host: TwoPhaseHost,
    act: ActFn,
    env_state: EnvState,
    carry: Any,
    key: jax.Array,
    length: int,
) -> tuple[EnvState, Any, Transition]:
    """`coherent_jax.agents.rollout.unroll` with the envs as ``len(groups)`` >= 2 groups in a ring
    whose physics overlaps the next group's policy (the module's docstring)."""
    k = len(groups)
    steps = [host.deferred(vec) for vec in groups]
    keys = jax.random.split(key, length)

    def act_g(g, step_key, state, carry_g):
        return act(jax.random.fold_in(step_key, g), carry_g, state.obs, state.first)

    def begin(g, state, out, go):
        return (host.start_step(groups[g], state, out.action, go), state, out)

    states, carries = split_env_state(env_state, k), split_groups(carry, k)
    last = k - 1  # group K-1's step 0 starts before the scan; each scan step starts its next one
    pending = begin(last, states[last], act_g(last, keys[0], states[last], carries[last]), jnp.asarray(True))

    def body(c, xs):
        states, carries, prev = list(c[0]), list(c[1]), c[2]  # prev: group K-1's step t, started
        step_key, next_key, go = xs
        transitions: list[Any] = [None] * k
        prev_g = last
        # Starts in ring order 0(t), ..., K-2(t), K-1(t+1); each start is followed by the
        # finish of the group started before it, whose physics ran under this group's policy.
        for g in range(k):
            if g < last:
                started = begin(g, states[g], act_g(g, step_key, states[g], carries[g]), jnp.asarray(True))
            else:  # group K-1 took step t at g = 0: its step t + 1, unless t is the last
                started = begin(g, states[g], act_g(g, next_key, states[g], carries[g]), go)
            ticket, before, out = prev
            nxt, outcome = steps[prev_g](before, out.action, ticket, started[0])
            transitions[prev_g] = _transition(before, out, outcome)
            states[prev_g], carries[prev_g] = nxt, out.carry
            prev, prev_g = started, g
        return (tuple(states), tuple(carries), prev), join_groups(transitions)

    go = jnp.arange(length) < length - 1
    next_keys = jnp.concatenate([keys[1:], keys[:1]])
    init = (tuple(states), tuple(carries), pending)
    (states, carries, _), data = jax.lax.scan(body, init, (keys, next_keys, go))
    return join_env_state(states), join_groups(carries), data
