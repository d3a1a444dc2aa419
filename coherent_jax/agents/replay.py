"""A replay buffer held as JAX arrays: a ring buffer inside the train state.

Because the buffer is a pytree of fixed-shape arrays, inserting a batch of
transitions and sampling minibatches are pure functions, so collecting K env steps
and doing U gradient updates compile into one jitted function (thesis Algorithm 3,
steps 5 and 9). Inserting past the capacity overwrites the oldest transitions;
sampling is uniform over the transitions stored so far.
"""

from __future__ import annotations

from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
from flax import struct


class Experience(NamedTuple):
    """Transitions (s, a, r, s', d) of thesis Algorithm 3, step 5; leading axis = batch.

    Attributes:
      obs: [..., o] s, raw (observation normalisation is applied when sampled).
      action: [..., p] a in [-1, 1], as executed.
      reward: [...] r.
      next_obs: [..., o] s', the state reached before any auto-reset.
      terminated: [...] d, 1.0 if s' is terminal (time-limit truncation is not: its
        value is bootstrapped).
    """

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    terminated: jax.Array


@struct.dataclass
class ReplayBuffer:
    """Ring buffer of `Experience` with capacity C.

    Attributes:
      data: `Experience` of arrays with leading axis C.
      position: index the next insert writes to.
      size: number of valid transitions, min(total inserted, C).
    """

    data: Experience
    position: jax.Array
    size: jax.Array

    @property
    def capacity(self) -> int:
        return self.data.reward.shape[0]


def replay_init(capacity: int, obs_size: int, action_size: int) -> ReplayBuffer:
    """An empty buffer of ``capacity`` transitions (float32 storage)."""
    if capacity < 1:
        raise ValueError(f"capacity must be >= 1, got {capacity}")
    f = lambda *shape: jnp.zeros((capacity, *shape), jnp.float32)  # noqa: E731
    return ReplayBuffer(
        data=Experience(f(obs_size), f(action_size), f(), f(obs_size), f()),
        position=jnp.zeros((), jnp.int32),
        size=jnp.zeros((), jnp.int32),
    )


def replay_add(buffer: ReplayBuffer, batch: Experience) -> ReplayBuffer:
    """Writes a batch of K <= C transitions at ``position``, wrapping around.

    Transition k goes to slot (position + k) mod C, so after the insert the buffer
    holds the last min(total, C) transitions ever inserted.
    """
    k = batch.reward.shape[0]
    capacity = buffer.capacity
    if k > capacity:
        raise ValueError(f"cannot insert {k} transitions into a buffer of capacity {capacity}")
    jax.tree.map(lambda b, d: chex.assert_equal_shape([b[0], d[0]]), batch, buffer.data)
    idx = (buffer.position + jnp.arange(k, dtype=jnp.int32)) % capacity
    data = jax.tree.map(lambda d, b: d.at[idx].set(b.astype(d.dtype)), buffer.data, batch)
    return ReplayBuffer(
        data=data,
        position=(buffer.position + k) % capacity,
        size=jnp.minimum(buffer.size + k, capacity),
    )


def replay_sample(buffer: ReplayBuffer, key: jax.Array, batch_size: int) -> Experience:
    """``batch_size`` transitions drawn uniformly, with replacement, from the valid ones.

    An empty buffer returns slot 0 (zeros); callers only sample after warm-up.
    """
    idx = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buffer.size, 1))
    return jax.tree.map(lambda d: d[idx], buffer.data)
