"""Coloured action noise (Eberhard et al. 2023, "Pink noise is all you need").

The Gaussian policy of `action.ActionNoise`, a = mean(s) + std xi_t, with the white
xi_t replaced by one coloured sequence per episode and action dimension, whose power
spectral density falls as

    S(f) ~ 1 / f^exponent        (0: white, 1: pink, 2: red / Brownian)

A sequence of length L is drawn in the frequency domain (Timmer & Koenig 1995): for
the frequencies f_k = k / L, k = 1..L/2, Fourier coefficients X_k with independent
N(0, s_k^2) real and imaginary parts (real only at the Nyquist frequency k = L/2),
s_k = f_k^(-exponent/2), X_0 = 0, and xi = irfft(X). Every xi_t is then Gaussian
with mean 0 and the same variance

    Var xi_t = (4 sum_{0<k<L/2} s_k^2 + s_{L/2}^2) / L^2     (L even; no Nyquist term if odd)

which the sequence is divided by, so xi_t ~ N(0, 1) marginally and only the
correlation across time changes with the exponent:

    Corr(xi_t, xi_{t+l}) = sum_k c_k s_k^2 cos(2 pi k l / L) / sum_k c_k s_k^2,
    c_k = 4 (0 < k < L/2), 1 (k = L/2).

As in the paper, the log-probability is the policy's own Gaussian N(mean, std^2)
per step (the marginal of every xi_t is N(0, 1)); only collection changes.
"""

from __future__ import annotations

from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np

from coherent_jax.exploration.action import ActionNoise, gaussian_log_prob
from coherent_jax.exploration.base import ActOutput, OffPolicyBehaviour
from coherent_jax.networks import squash
from coherent_jax.sweep_axis import any_point


def spectrum_scales(length: int, exponent: float) -> np.ndarray:
    """Amplitudes s_k = f_k^(-exponent/2) for k = 0..L//2 (s_0 = 0), float64 [L//2 + 1]."""
    k = np.arange(length // 2 + 1, dtype=np.float64)
    scales = np.zeros_like(k)
    scales[1:] = (k[1:] / length) ** (-exponent / 2.0)
    return scales


def _coefficient_weights(length: int) -> np.ndarray:
    """c_k of the module docstring: 4 for 0 < k < L/2, 1 at the Nyquist bin of an even L, 0 at k = 0."""
    weights = np.full(length // 2 + 1, 4.0)
    weights[0] = 0.0
    if length % 2 == 0:
        weights[-1] = 1.0
    return weights


def coloured_noise(key: chex.PRNGKey, exponent: float, length: int, shape: tuple[int, ...] = ()) -> jax.Array:
    """Unit-variance Gaussian noise with spectrum 1/f^exponent along the first axis.

    Args:
      key: PRNG key.
      exponent: spectral exponent (static): 0 white, 1 pink, 2 red.
      length: L, the number of time steps (>= 2).
      shape: trailing shape; every trailing index is an independent sequence.

    Returns:
      xi [L, *shape], every xi_t ~ N(0, 1).
    """
    if length < 2:
        raise ValueError(f"coloured noise needs length >= 2, got {length}")
    scales = spectrum_scales(length, exponent)
    var = float(np.sum(_coefficient_weights(length) * scales**2)) / length**2
    k_re, k_im = jax.random.split(key)
    n_freq = scales.shape[0]
    re = jax.random.normal(k_re, (n_freq, *shape))
    im = jax.random.normal(k_im, (n_freq, *shape))
    if length % 2 == 0:  # the Nyquist coefficient of a real signal is real
        im = im.at[-1].set(0.0)
    s = jnp.asarray(scales, jnp.float32).reshape((n_freq,) + (1,) * len(shape))
    spectrum = s * (re + 1j * im)
    return jnp.fft.irfft(spectrum, n=length, axis=0) / np.sqrt(var)


def autocorrelation(length: int, exponent: float, lag: int) -> float:
    """Corr(xi_t, xi_{t+lag}) of `coloured_noise` (module docstring), float64."""
    scales = spectrum_scales(length, exponent)
    weights = _coefficient_weights(length) * scales**2
    k = np.arange(scales.shape[0])
    return float(np.sum(weights * np.cos(2.0 * np.pi * k * lag / length)) / np.sum(weights))


class PinkCarry(NamedTuple):
    """Per-env state: the episode's noise sequence and the step within it.

    Attributes:
      noise: [n, L, p] this episode's coloured sequence (unit variance).
      step: [n] int32, index of the next step's noise (reset to 0 at an episode start).
    """

    noise: jax.Array
    step: jax.Array


def draw_episode_noise(key: chex.PRNGKey, exponent: float, length: int, num_envs: int, action_size: int):
    """One coloured sequence per env for a whole episode, [n, L, p]."""
    noise = coloured_noise(key, exponent, length, (num_envs, action_size))
    return jnp.moveaxis(noise, 0, 1)


def init_pink_carry(key: chex.PRNGKey, exponent: float, length: int, num_envs: int, action_size: int):
    return PinkCarry(
        noise=draw_episode_noise(key, exponent, length, num_envs, action_size),
        step=jnp.zeros((num_envs,), jnp.int32),
    )


def next_noise(key: chex.PRNGKey, carry: PinkCarry, first: chex.Array, exponent: float):
    """xi [n, p] for this step of every env, drawing a new sequence where an episode starts."""
    chex.assert_rank(first, 1)
    num_envs, length, action_size = carry.noise.shape
    noise = jax.lax.cond(
        any_point(jnp.any(first)),
        lambda: jnp.where(
            first[:, None, None],
            draw_episode_noise(key, exponent, length, num_envs, action_size),
            carry.noise,
        ),
        lambda: carry.noise,
    )
    step = jnp.where(first, 0, carry.step)
    xi = noise[jnp.arange(num_envs), step % length]  # [n, p]
    return xi, PinkCarry(noise=noise, step=step + 1)


class PinkNoise(ActionNoise):
    """Gaussian policy whose collection noise is coloured, one sequence per episode.

    ``length`` is the episode length (the time limit), so one sequence covers an
    episode; a longer episode would wrap around (cannot happen with the time limit).
    """

    name = "pink"

    def __init__(
        self, action_size: int, hidden, activation: str, init_std: float, exponent: float, length: int
    ):
        super().__init__(action_size, hidden, activation, init_std)
        self.exponent = float(exponent)
        self.length = int(length)

    @classmethod
    def from_config(cls, cfg, action_size: int):
        hidden, activation = cfg.policy_hidden, cfg.activation
        return cls(action_size, hidden, activation, cfg.init_std, cfg.pink.exponent, cfg.episode_length)

    def init_carry(self, key, params, hparams, num_envs):
        return init_pink_carry(key, self.exponent, self.length, num_envs, self.action_size)

    def act(self, key, params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        mean = self._mean(params, obs)
        log_std = jnp.broadcast_to(params["log_std"], mean.shape)
        xi, carry = next_noise(key, carry, first, self.exponent)
        action = mean + jnp.exp(log_std) * xi
        return ActOutput(action, gaussian_log_prob(action, mean, log_std), carry)


class PinkBehaviour(OffPolicyBehaviour):
    """SAC's own sample tanh(mean + std xi) with the coloured xi (Eberhard et al. §4)."""

    name = "pink"

    def __init__(self, action_size: int, exponent: float, length: int):
        self.action_size = int(action_size)
        self.exponent = float(exponent)
        self.length = int(length)

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(action_size, cfg.pink.exponent, cfg.episode_length)

    def init_carry(self, key, actor, actor_params, hparams, num_envs):
        return init_pink_carry(key, self.exponent, self.length, num_envs, self.action_size)

    def act(self, key, actor, actor_params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        xi, carry = next_noise(key, carry, first, self.exponent)
        action, _ = squash(key, actor.dist(actor_params, obs), noise=xi)
        return action, carry
