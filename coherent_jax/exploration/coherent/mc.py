"""The coherent strategy's ablations (thesis §5): Monte Carlo integration, every layer.

``coherent.integration=mc`` (`CoherentMC`): the same exploration as
`coherent.CoherentExploration` (the beta-chain on the last layer, eqs. 4.1-4.5, and
a_t ~ N(w_t xh_t, action_std^2), eq. 4.29), but the loss scores a_t under the
*sampled* weights instead of integrating them out:

    log p(a_t | w_t, s_t) = log N(a_t; w_t xh_t, diag(action_std^2)),
    w_t = mu + w_std z_t,                                       (single-sample eq. 4.8)

with z_t the standardised chain of collection, stored per step as the strategy's
extras, so the gradient reaches mu and w_std through w_t (the reparameterisation of
a single sample, as NoisyNets and PSNE do).

``coherent.layers=all`` (`CoherentAllLayers`): the chain runs over every layer's
weights and biases, w_t = mu + w_std z_t per layer with the same beta, and the loss is
the single-sample log N(a_t; f_{w_t}(s_t), action_std^2) (only the last layer enters
the action linearly, so only it integrates analytically). Each layer's w_std starts
at w_std_init sqrt(q / fan_in), q the last layer's input size: the last layer starts
as in ``layers=last`` and every layer's pre-activation noise has a similar scale.
"""

from __future__ import annotations

import math

import chex
import jax
import jax.numpy as jnp

from coherent_jax.exploration.action import gaussian_entropy, gaussian_log_prob
from coherent_jax.exploration.base import ActOutput, SegmentLogProb
from coherent_jax.exploration.chain import chain_step
from coherent_jax.exploration.coherent.layer import ChainStrategy, LastLayer
from coherent_jax.networks import ACTIVATIONS, augment


class CoherentMC(ChainStrategy):
    """Coherent exploration of the last layer scored by single-sample Monte Carlo.

    The policy (`layer.LastLayer`: parameters, the weights the chain runs with,
    the evaluation action) is that of `strategy.CoherentExploration`; only the per-env
    carry (the chain's z) and the log-probability differ.
    """

    name = "coherent-mc"

    def __init__(
        self,
        action_size: int,
        hidden,
        activation: str,
        beta: float,
        w_std_init: float,
        action_std: float,
        learn_action_std: bool = False,
    ):
        super().__init__(action_size, beta, w_std_init, action_std, learn_action_std)
        self.layer = LastLayer(action_size, hidden, activation, w_std_init)

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(action_size, cfg.policy_hidden, cfg.activation, **cls.chain_settings(cfg))

    def init(self, key, obs_size):
        return {**self.layer.init(key, obs_size), **self._action_std_params()}

    def _head(self, params, hparams):
        return self.layer.weights(params, self._action_std(params, hparams))

    def init_carry(self, key, params, hparams, num_envs):
        return jnp.zeros((num_envs,) + params["mu"].shape, jnp.float32)

    def _action_log_prob(self, params, hparams, z, x, actions):
        mu, w_std, action_std = self._head(params, hparams)
        mean = jnp.einsum("...pk,...k->...p", mu + w_std * z, augment(x))
        log_std = jnp.broadcast_to(jnp.log(action_std), mean.shape)
        return gaussian_log_prob(actions, mean, log_std), log_std

    def act(self, key, params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        k_z, k_a = jax.random.split(key)
        mu, w_std, action_std = self._head(params, hparams)
        z = chain_step(k_z, carry, first, hparams.beta)
        x = self.layer.features(params, obs)
        mean = jnp.einsum("npk,nk->np", mu + w_std * z, augment(x))
        action = mean + action_std * jax.random.normal(k_a, mean.shape, mean.dtype)
        logp, _ = self._action_log_prob(params, hparams, z, x, action)
        return ActOutput(action, logp, z, extras=z)

    def log_prob(self, params, hparams, segment):
        segment.check()
        chex.assert_rank(segment.extras, 3)  # the chain's z [T, p, q+1]
        x = self.layer.features(params, segment.obs)
        logp, log_std = self._action_log_prob(params, hparams, segment.extras, x, segment.action)
        return SegmentLogProb(logp, gaussian_entropy(log_std))

    def mean_action(self, params, obs):
        return self.layer.mean_action(params, obs)

    def metrics(self, params, hparams):
        _, w_std, action_std = self._head(params, hparams)
        return self._chain_metrics(jnp.mean(w_std), action_std, hparams)


class CoherentAllLayers(ChainStrategy):
    """The beta-chain over every layer's weights, single-sample gradients (thesis §5 ablation)."""

    name = "coherent-all"

    def __init__(
        self,
        action_size: int,
        hidden,
        activation: str,
        beta: float,
        w_std_init: float,
        action_std: float,
        learn_action_std: bool = False,
    ):
        super().__init__(action_size, beta, w_std_init, action_std, learn_action_std)
        self.hidden = tuple(int(h) for h in hidden)
        self.activation = ACTIVATIONS[activation]

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(action_size, cfg.policy_hidden, cfg.activation, **cls.chain_settings(cfg))

    def init(self, key, obs_size):
        sizes = (obs_size, *self.hidden, self.action_size)
        q = self.hidden[-1]
        mu, log_w_std = [], []
        for i, (m, k) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
            key, sub = jax.random.split(key)
            gain = 0.01 if i == len(sizes) - 2 else math.sqrt(2.0)
            mu.append(
                {
                    "w": jax.nn.initializers.orthogonal(gain)(sub, (m, k), jnp.float32),
                    "b": jnp.zeros((k,), jnp.float32),
                }
            )
            log_s = math.log(self.w_std_init * math.sqrt(q / m))
            log_w_std.append(
                {"w": jnp.full((m, k), log_s, jnp.float32), "b": jnp.full((k,), log_s, jnp.float32)}
            )
        return {"mu": mu, "log_w_std": log_w_std, **self._action_std_params()}

    def init_carry(self, key, params, hparams, num_envs):
        return jax.tree.map(lambda v: jnp.zeros((num_envs,) + v.shape, v.dtype), params["mu"])

    def _forward(self, layers, obs):
        """The network with weights ``layers`` (one set), obs [o] -> [p]."""
        x = obs
        for i, layer in enumerate(layers):
            x = x @ layer["w"] + layer["b"]
            if i < len(layers) - 1:
                x = self.activation(x)
        return x

    def _sampled_mean(self, params, z, obs):
        """f_{mu + w_std z}(s) for a batch: z leaves [B, ...], obs [B, o] -> [B, p]."""
        w_std = jax.tree.map(jnp.exp, params["log_w_std"])

        def one(z_b, o_b):
            layers = jax.tree.map(lambda m, s, zz: m + s * zz, params["mu"], w_std, z_b)
            return self._forward(layers, o_b)

        return jax.vmap(one)(z, obs)

    def act(self, key, params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        leaves, treedef = jax.tree.flatten(carry)
        keys = jax.random.split(key, len(leaves) + 1)
        z = jax.tree.unflatten(
            treedef,
            [chain_step(k, leaf, first, hparams.beta) for k, leaf in zip(keys[1:], leaves, strict=True)],
        )
        mean = self._sampled_mean(params, z, obs)
        action_std = self._action_std(params, hparams)
        action = mean + action_std * jax.random.normal(keys[0], mean.shape, mean.dtype)
        log_std = jnp.broadcast_to(jnp.log(action_std), mean.shape)
        return ActOutput(action, gaussian_log_prob(action, mean, log_std), z, extras=z)

    def log_prob(self, params, hparams, segment):
        segment.check()
        mean = self._sampled_mean(params, segment.extras, segment.obs)
        log_std = jnp.broadcast_to(jnp.log(self._action_std(params, hparams)), mean.shape)
        return SegmentLogProb(gaussian_log_prob(segment.action, mean, log_std), gaussian_entropy(log_std))

    def mean_action(self, params, obs):
        flat = obs.reshape(-1, obs.shape[-1])
        out = jax.vmap(lambda o: self._forward(params["mu"], o))(flat)
        return out.reshape(obs.shape[:-1] + (self.action_size,))

    def metrics(self, params, hparams):
        stds = [jnp.mean(jnp.exp(v)) for v in jax.tree.leaves(params["log_w_std"])]
        return self._chain_metrics(jnp.mean(jnp.stack(stds)), self._action_std(params, hparams), hparams)
