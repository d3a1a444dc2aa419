"""Lattice: latent time-correlated exploration (Chiappa, Marin Vargas, Huang, Mathis, NeurIPS 2023).

Lattice generalises gSDE (`gsde.py`). The policy's last latent layer x = f_theta(s)
(the trunk output, d features) feeds the linear mean head, mean = W' x + b with the
head's kernel W [d, p]. Two random matrices, held for ``resample_every`` steps (paper,
Figure 1C) and redrawn at each episode start as gSDE's are here (the reference code
redraws at each rollout's start instead), perturb it:

    latent noise   P_x [d, d],  (P_x)_ij ~ N(0, sigma_x,ij^2),  x~ = x + alpha P_x' x
    action noise   P_a [d, p],  (P_a)_ij ~ N(0, sigma_a,ij^2)
    a = W' x~ + b + P_a' x = mean(s) + alpha W' (P_x' x) + P_a' x        (paper, Methods)

The latent perturbation propagates through the last layer, so the action noise is
correlated across action dimensions; with alpha = 0 it is gSDE's noise. Given the
state, the P are Gaussian and the noise is linear in them, so the action is Gaussian
with the full covariance (paper, Methods: "a multivariate Gaussian with a full covariance")

    Sigma(x) = alpha^2 W' diag(sigma_x^2' x^2) W + diag(sigma_a^2' x^2) + std_reg^2 I

(x^2 elementwise; the k-th latent's noise has variance sum_i x_i^2 sigma_x,ik^2). Its
Cholesky factor gives the log-probability and the entropy the on-policy losses use.

What follows the reference implementation (amathislab/lattice,
``src/models/distributions.py``, ``LatticeStateDependentNoiseDistribution`` with its
defaults ``full_std=True``, ``learn_features=False``; the paper's equation numbers
are not cited: each formula was checked against the reference code, not the paper's text):

* the stds: one learned log-std per entry ("full std", [d, d + p]: P_x's then P_a's;
  the reference's PPO scripts pass ``full_std=False``, one per latent row),
  clipped to [log 1e-3, log 10] (``std_clip`` as the reference's policies pass it;
  no gradient outside the range), then scaled by 1/sqrt(d) so that the action's std
  does not grow with the width of the layer: with features of unit mean square the
  action noise of P_a has std s = ``lattice.init_std`` at the start (as gSDE's);
* the features x enter the noise and the covariance through a stop-gradient
  (``learn_features=False``): the variance trains the stds and W, the trunk is
  shaped by the mean;
* W in the covariance is the mean head's kernel with its gradient (the reference
  code does not detach it); ``lattice.weight_grad=false`` detaches it, so the
  covariance then trains the stds alone;
* ``lattice.alpha`` weighs the latent noise (the reference's ``alpha``, 0 removes it),
  ``lattice.action_noise=false`` removes P_a (latent noise alone), and
  ``lattice.std_reg`` adds std_reg^2 to every action variance (the reference's
  ``std_reg``). The reference adds std_reg^2 to the covariance without drawing that
  noise; here it is drawn, white, at every step, so that the stored log-probability
  is the density of the action taken.

The mean head starts at orthogonal gain ``lattice.head_gain``, by default every
strategy's 0.01. The latent noise reaches the action through W, so at the start it is
about g^2 = 1e-4 of the action's variance (Lattice begins as gSDE) and grows with W as
the mean is learned (on HalfCheetah W's columns reached norms 0.4-0.6 by 400k steps).
The reference's PPO runs start W at PyTorch's default linear layer (``ortho_init=False``,
column norm about 1/sqrt(3)), where the latent noise is a quarter of the variance from
the start: ``lattice.head_gain=0.57735`` does that, at the price of initial mean actions
of std about 0.3; on HalfCheetah-PPO it learned more slowly (docs/strategies.md).

A floor of 1e-6 on the diagonal (not drawn, as gSDE's) keeps the Cholesky factor
finite where every feature vanishes. With SAC, `LatticeBehaviour` supplies SAC's xi,
and its actor's mean head starts at ``lattice.head_gain`` too.
"""

from __future__ import annotations

import math

import chex
import jax
import jax.numpy as jnp

from coherent_jax.exploration.base import ActOutput, OffPolicyBehaviour, OnPolicyStrategy, SegmentLogProb
from coherent_jax.exploration.gsde import init_gsde_carry, next_z
from coherent_jax.exploration.linalg import whiten
from coherent_jax.networks import HEAD_GAIN, ActorDist, MeanHead, squash

STD_MIN, STD_MAX = 1e-3, 10.0  # the clip range of the learned stds (the reference's std_clip)
_VAR_FLOOR = 1e-6
_LOG_2PI = math.log(2.0 * math.pi)


def lattice_stds(log_std: chex.Array, latent_size: int) -> tuple[chex.Array, chex.Array]:
    """(sigma_x [d, d], sigma_a [d, p]) from the learned log-stds [d, d + p]: clipped to
    [STD_MIN, STD_MAX], then divided by sqrt(d). sigma_a is [d, 0] without action noise."""
    clipped = jnp.clip(log_std, math.log(STD_MIN), math.log(STD_MAX)) - 0.5 * math.log(latent_size)
    std = jnp.exp(clipped)
    return std[:, :latent_size], std[:, latent_size:]


def lattice_cov(
    x: chex.Array,
    kernel: chex.Array,
    sigma_x: chex.Array,
    sigma_a: chex.Array,
    alpha: float,
    std_reg: float,
) -> chex.Array:
    """Sigma(x) [..., p, p] of the module docstring, for features x [..., d] and the mean
    head's kernel W [d, p] (mean = x W + b); no action-noise term if sigma_a is [d, 0]."""
    x2 = jnp.square(x)
    latent_var = x2 @ jnp.square(sigma_x)  # [..., d]
    cov = alpha**2 * jnp.einsum("ip,...i,iq->...pq", kernel, latent_var, kernel)
    diag = jnp.full(cov.shape[:-1], std_reg**2 + _VAR_FLOOR, cov.dtype)
    if sigma_a.shape[-1]:
        diag = diag + x2 @ jnp.square(sigma_a)
    return cov + diag[..., None] * jnp.eye(cov.shape[-1], dtype=cov.dtype)


def mvn_log_prob_entropy(x: chex.Array, mean: chex.Array, cov: chex.Array) -> tuple[chex.Array, chex.Array]:
    """log N(x; mean, cov) and the Gaussian's entropy, by the Cholesky factor cov = L L':
    log p = -|L^-1 (x - mean)|^2 / 2 - sum log L_ii - p log(2 pi) / 2,
    H = sum log L_ii + p (1 + log(2 pi)) / 2.

    The factor and its reverse pass are `linalg.whiten`'s, vectorised across the batch of
    small matrices (JAX's own triangular solve and its reverse pass run matrix by matrix on
    CPU); ``cov`` is symmetric by construction, as `whiten` requires.
    """
    resid = x - mean
    white, log_diag, _ = whiten(cov, resid, jnp.zeros((*resid.shape, 0), resid.dtype))
    half_logdet = jnp.sum(log_diag, axis=-1)
    p = x.shape[-1]
    log_prob = -0.5 * jnp.sum(jnp.square(white), axis=-1) - half_logdet - 0.5 * p * _LOG_2PI
    return log_prob, half_logdet + 0.5 * p * (1.0 + _LOG_2PI)


def lattice_noise(x: chex.Array, kernel: chex.Array, z: chex.Array, alpha: float, action_noise: bool):
    """alpha W' (P_x' x) + P_a' x, a - mean(s) of the module docstring, for features x [n, d],
    the noise matrices z [n, d, d (+ p)] (P_x, then P_a if ``action_noise``: the standard-normal
    draw times its stds) and the head's kernel W [d, p]."""
    d = x.shape[-1]
    noise = alpha * jnp.einsum("nd,nde->ne", x, z[..., :d]) @ kernel
    if action_noise:
        noise = noise + jnp.einsum("nd,ndp->np", x, z[..., d:])
    return noise


class Lattice(OnPolicyStrategy):
    """Lattice for A2C/PPO (see the module docstring)."""

    name = "lattice"

    def __init__(
        self,
        action_size: int,
        hidden,
        activation: str,
        init_std: float,
        resample_every: int,
        alpha: float = 1.0,
        action_noise: bool = True,
        weight_grad: bool = True,
        std_reg: float = 0.0,
        head_gain: float = HEAD_GAIN,
    ):
        self.action_size = int(action_size)
        self.latent_size = int(hidden[-1])
        self.net = MeanHead(tuple(hidden), activation, self.action_size, head_gain=float(head_gain))
        self.init_std = float(init_std)
        self.resample_every = int(resample_every)
        self.alpha = float(alpha)
        self.action_noise = bool(action_noise)
        self.weight_grad = bool(weight_grad)
        self.std_reg = float(std_reg)

    @classmethod
    def from_config(cls, cfg, action_size: int):
        lc = cfg.lattice
        return cls(
            action_size,
            cfg.policy_hidden,
            cfg.activation,
            lc.init_std,
            lc.resample_every,
            lc.alpha,
            lc.action_noise,
            lc.weight_grad,
            lc.std_reg,
            lc.head_gain,
        )

    @property
    def _noise_columns(self) -> int:
        """Columns of the [d, .] noise draw: P_x's d, then P_a's p if there is action noise."""
        return self.latent_size + (self.action_size if self.action_noise else 0)

    def init(self, key, obs_size):
        return {
            "net": self.net.init(key, jnp.zeros((1, obs_size))),
            "log_std": jnp.full(
                (self.latent_size, self._noise_columns), math.log(self.init_std), jnp.float32
            ),
        }

    def init_carry(self, key, params, hparams, num_envs):
        return init_gsde_carry(key, num_envs, self.latent_size, self._noise_columns)

    def _kernel(self, params):
        return params["net"]["params"]["Dense_0"]["kernel"]

    def _dist(self, params, obs):
        """(x, mean, Sigma(x)) for obs [..., o]; x through a stop-gradient."""
        x, mean = self.net.apply(params["net"], obs)
        x = jax.lax.stop_gradient(x)
        kernel = self._kernel(params)
        kernel = kernel if self.weight_grad else jax.lax.stop_gradient(kernel)
        sigma_x, sigma_a = lattice_stds(params["log_std"], self.latent_size)
        return x, mean, lattice_cov(x, kernel, sigma_x, sigma_a, self.alpha, self.std_reg)

    def act(self, key, params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        k_z, k_white = jax.random.split(key)
        x, mean, cov = self._dist(params, obs)
        z, carry = next_z(k_z, carry, first, self.resample_every)
        stds = jnp.concatenate(lattice_stds(params["log_std"], self.latent_size), axis=-1)
        noise = lattice_noise(x, self._kernel(params), stds * z, self.alpha, self.action_noise)
        if self.std_reg > 0.0:
            noise = noise + self.std_reg * jax.random.normal(k_white, mean.shape, mean.dtype)
        action = mean + noise
        return ActOutput(action, mvn_log_prob_entropy(action, mean, cov)[0], carry)

    def log_prob(self, params, hparams, segment):
        segment.check()
        _, mean, cov = self._dist(params, segment.obs)
        return SegmentLogProb(*mvn_log_prob_entropy(segment.action, mean, cov))

    def mean_action(self, params, obs):
        return self.net.apply(params["net"], obs)[1]

    def metrics(self, params, hparams):
        std = jnp.exp(jnp.clip(params["log_std"], math.log(STD_MIN), math.log(STD_MAX)))
        out = {"lattice_std_x": jnp.mean(std[:, : self.latent_size])}
        if self.action_noise:
            out["lattice_std_a"] = jnp.mean(std[:, self.latent_size :])
        return out


class LatticeBehaviour(OffPolicyBehaviour):
    """Lattice's noise as the xi of SAC's sample tanh(mean + std xi).

    SAC's actor keeps its own state-dependent std (plain SAC's update, unchanged); Lattice
    shapes only the direction of its noise, as gSDE's behaviour does. With unit stds
    scaled by 1/|x| (gSDE's sigma_ij = 1/|x|) the noise e = alpha W' (Z_x' x) + Z_a' x
    of the actor's mean head W (its kernel, detached) is N(0, alpha^2 W'W + I) given
    the state, and each dimension is divided by its std:

        xi_j = e_j / (|x| sqrt(alpha^2 |W_:j|^2 + 1))        (the 1 without action noise: 0)

    so xi_j ~ N(0, 1) at every state, correlated across action dimensions through the
    mean head and, with Z held for n steps, smooth along the trajectory. This departs
    from the reference's Lattice-SAC, whose actor is the full-covariance Gaussian
    itself; here SAC's actor and update stay those of every other strategy.
    ``lattice.init_std`` and ``lattice.std_reg`` scale the on-policy noise only.
    """

    name = "lattice"

    def __init__(
        self,
        resample_every: int,
        alpha: float = 1.0,
        action_noise: bool = True,
        head_gain: float = HEAD_GAIN,
    ):
        self.resample_every = int(resample_every)
        self.alpha = float(alpha)
        self.action_noise = bool(action_noise)
        self.actor_head_gain = float(head_gain)

    @classmethod
    def from_config(cls, cfg, action_size: int):
        lc = cfg.lattice
        return cls(lc.resample_every, lc.alpha, lc.action_noise, lc.head_gain)

    def init_carry(self, key, actor, actor_params, hparams, num_envs):
        q = actor.feature_size
        return init_gsde_carry(key, num_envs, q, q + (actor.action_size if self.action_noise else 0))

    def act(self, key, actor, actor_params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        z, carry = next_z(key, carry, first, self.resample_every)
        x = actor.features(actor_params, obs)
        kernel = jax.lax.stop_gradient(actor_params["mu"][:, : actor.feature_size].T)  # [q, p]
        noise = lattice_noise(x, kernel, z, self.alpha, self.action_noise)
        scale = self.alpha**2 * jnp.sum(jnp.square(kernel), axis=0) + float(self.action_noise)  # [p]
        norm2 = jnp.sum(jnp.square(x), -1, keepdims=True)
        xi = noise / jnp.sqrt(norm2 * scale + _VAR_FLOOR)
        dist: ActorDist = actor.dist_from_features(actor_params, x)
        action, _ = squash(key, dist, noise=xi)
        return action, carry
