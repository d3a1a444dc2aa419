"""NoisyNets for continuous control (Fortunato et al. 2018), factorised Gaussian noise.

Every linear layer of the policy (trunk and mean head) is noisy: with input size m,
output size k and per-episode noise eps_in [m], eps_out [k],

    W = mu_W + sigma_W * (f(eps_in) f(eps_out)^T),   b = mu_b + sigma_b * f(eps_out),
    f(e) = sign(e) sqrt(|e|)                                      (Fortunato et al., eq. 11)

with mu and sigma learned (sigma starts at sigma_0 / sqrt(m), their §3.2). The noise
is drawn at each episode start and held for the episode (trajectory-based, thesis
Figure 4.1 middle). The policy stays Gaussian, a ~ N(f_{mu,sigma,eps}(s), std^2) with a
learned state-independent std, and the loss uses the single-sample Monte Carlo
estimate of thesis eq. (4.8): the log-probability under the noise that was sampled
during collection, stored per step as the strategy's extras, so PPO's ratio compares
the same sampled network under old and new (mu, sigma).

The layer is evaluated without forming a per-env weight matrix:
x W = x mu_W + ((x * f(eps_in)) sigma_W) * f(eps_out).
"""

from __future__ import annotations

import math

import chex
import jax
import jax.numpy as jnp

from coherent_jax.exploration.action import gaussian_entropy, gaussian_log_prob
from coherent_jax.exploration.base import ActOutput, OnPolicyStrategy, SegmentLogProb
from coherent_jax.networks import ACTIVATIONS


def factorised(e: chex.Array) -> chex.Array:
    """f(e) = sign(e) sqrt(|e|) (Fortunato et al. §3.2)."""
    return jnp.sign(e) * jnp.sqrt(jnp.abs(e))


def noisy_dense(layer: dict, x: chex.Array, eps_in: chex.Array | None, eps_out: chex.Array | None):
    """One factorised noisy layer, x [..., m] -> [..., k]; ``eps_*`` None = the mean layer.

    ``eps_in`` [..., m] and ``eps_out`` [..., k] carry the batch dims of x (one
    noise draw per env).
    """
    y = x @ layer["w_mu"] + layer["b_mu"]
    if eps_in is None:
        return y
    f_in, f_out = factorised(eps_in), factorised(eps_out)
    return y + ((x * f_in) @ layer["w_sigma"]) * f_out + layer["b_sigma"] * f_out


class NoisyNet(OnPolicyStrategy):
    """Gaussian policy whose every linear layer is a factorised NoisyNet layer."""

    name = "noisynet"

    def __init__(self, action_size: int, hidden, activation: str, init_std: float, sigma0: float):
        self.action_size = int(action_size)
        self.hidden = tuple(int(h) for h in hidden)
        self.activation = ACTIVATIONS[activation]
        self.init_std = float(init_std)
        self.sigma0 = float(sigma0)

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(action_size, cfg.policy_hidden, cfg.activation, cfg.init_std, cfg.noisynet.sigma0)

    def _sizes(self, obs_size):
        sizes = (obs_size, *self.hidden, self.action_size)
        return list(zip(sizes[:-1], sizes[1:], strict=True))

    def init(self, key, obs_size):
        layers = []
        pairs = self._sizes(obs_size)
        for i, (m, k) in enumerate(pairs):
            key, sub = jax.random.split(key)
            gain = 0.01 if i == len(pairs) - 1 else math.sqrt(2.0)  # as the other policies' layers
            layers.append(
                {
                    "w_mu": jax.nn.initializers.orthogonal(gain)(sub, (m, k), jnp.float32),
                    "b_mu": jnp.zeros((k,), jnp.float32),
                    "w_sigma": jnp.full((m, k), self.sigma0 / math.sqrt(m), jnp.float32),
                    "b_sigma": jnp.full((k,), self.sigma0 / math.sqrt(m), jnp.float32),
                }
            )
        return {
            "layers": layers,
            "log_std": jnp.full((self.action_size,), math.log(self.init_std), jnp.float32),
        }

    def _draw(self, key, params, num_envs):
        """Fresh factorised noise, a list of {"in": [n, m], "out": [n, k]} per layer."""
        noise = []
        for layer in params["layers"]:
            key, k_in, k_out = jax.random.split(key, 3)
            m, k = layer["w_mu"].shape
            noise.append(
                {
                    "in": jax.random.normal(k_in, (num_envs, m), jnp.float32),
                    "out": jax.random.normal(k_out, (num_envs, k), jnp.float32),
                }
            )
        return noise

    def init_carry(self, key, params, hparams, num_envs):
        return self._draw(key, params, num_envs)

    def _forward(self, params, obs, noise):
        x = obs
        layers = params["layers"]
        for i, layer in enumerate(layers):
            eps = noise[i] if noise is not None else {"in": None, "out": None}
            x = noisy_dense(layer, x, eps["in"], eps["out"])
            if i < len(layers) - 1:
                x = self.activation(x)
        return x

    def act(self, key, params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        k_noise, k_a = jax.random.split(key)
        fresh = self._draw(k_noise, params, obs.shape[0])
        # A new network per env at each episode start, held until the next one.
        noise = jax.tree.map(lambda new, old: jnp.where(first[:, None], new, old), fresh, carry)
        mean = self._forward(params, obs, noise)
        log_std = jnp.broadcast_to(params["log_std"], mean.shape)
        action = mean + jnp.exp(log_std) * jax.random.normal(k_a, mean.shape, mean.dtype)
        return ActOutput(action, gaussian_log_prob(action, mean, log_std), noise, extras=noise)

    def log_prob(self, params, hparams, segment):
        segment.check()  # every layer's noise [T, ...] among the extras
        mean = self._forward(params, segment.obs, segment.extras)  # the noise sampled at each step
        log_std = jnp.broadcast_to(params["log_std"], mean.shape)
        return SegmentLogProb(gaussian_log_prob(segment.action, mean, log_std), gaussian_entropy(log_std))

    def mean_action(self, params, obs):
        return self._forward(params, obs, None)

    def metrics(self, params, hparams):
        sigmas = [jnp.mean(jnp.abs(layer["w_sigma"])) for layer in params["layers"]]
        return {
            "action_std": jnp.mean(jnp.exp(params["log_std"])),
            "noisy_sigma_last": sigmas[-1],
            "noisy_sigma_mean": jnp.mean(jnp.stack(sigmas)),
        }
