"""Adaptive parameter-noise scale (Plappert et al. 2018; thesis §4.3, eqs. 4.50-4.51).

Off-policy training cannot learn the size of the noise injected in parameter
space, so it is adapted by how much of it shows in action space: the distance
between the (mean) actions of the unperturbed and a perturbed policy on a batch B
of replay states,

    d(pi, pi~) = sqrt( 1/(N |B|) sum_{i=1}^N sum_{s in B} (pi(s)_i - pi~(s)_i)^2 )      (4.50)

and sigma grows by alpha while d < delta, shrinks by alpha otherwise:

    sigma_{k+1} = alpha sigma_k   if d(pi, pi~) < delta,   sigma_k / alpha   otherwise  (4.51)

It stands alone, small, because two strategies share it (PSNE and Coherent-SAC) and
neither owns the other.
"""

from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
from flax import struct


def policy_distance(actions: jax.Array, perturbed_actions: jax.Array) -> jax.Array:
    """Eq. (4.50): root mean square difference over batch and action dims, [B, N] -> scalar."""
    chex.assert_rank(actions, 2)
    chex.assert_equal_shape([actions, perturbed_actions])
    return jnp.sqrt(jnp.mean(jnp.square(actions - perturbed_actions)))


def adapt_sigma(sigma: jax.Array, distance: jax.Array, delta: jax.Array, alpha: jax.Array) -> jax.Array:
    """Eq. (4.51): alpha * sigma if distance < delta, else sigma / alpha."""
    return jnp.where(distance < delta, sigma * alpha, sigma / alpha)


@struct.dataclass
class SigmaHParams:
    """The sweepable scalars of (4.51) in the train state (fields in sorted order, so the
    flattened leaves are those of the string-keyed dict this replaced).

    Attributes:
      sigma: the current noise scale sigma_k, or None where it is per-env state (the carry).
      sigma_alpha: the factor alpha.
      sigma_delta: the threshold delta.
    """

    sigma: jax.Array | None
    sigma_alpha: jax.Array
    sigma_delta: jax.Array


@dataclasses.dataclass(frozen=True)
class SigmaRule:
    """The settings of (4.51): the initial sigma, the threshold delta and the factor alpha."""

    sigma_init: float
    sigma_delta: float
    sigma_alpha: float

    @classmethod
    def from_options(cls, options) -> SigmaRule:
        """The rule of a settings group that holds it: ``cfg.psne`` or ``cfg.coherent_sac``."""
        return cls(float(options.sigma_init), float(options.sigma_delta), float(options.sigma_alpha))

    def hparams(self, with_sigma: bool = True) -> SigmaHParams:
        """Sweepable scalars: delta, alpha and (where it is not per-env state) sigma itself."""
        f = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        sigma = f(self.sigma_init) if with_sigma else None
        return SigmaHParams(sigma=sigma, sigma_alpha=f(self.sigma_alpha), sigma_delta=f(self.sigma_delta))
