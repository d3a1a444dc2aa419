"""What the on-policy strategies on the beta-chain share (thesis §4.1).

`ChainStrategy` holds the chain's settings (beta, the initial w_std, the action noise);
every coherent on-policy strategy (`strategy.CoherentExploration` and the ablations of
`mc`) is one. `LastLayer` is the policy whose last layer the chain perturbs:
the trunk f_theta and the last layer's weight mean and spread. The analytic strategy
and its Monte Carlo ablation each hold one and differ only in how they score an
action, so neither derives from the other.
"""

from __future__ import annotations

import math

import chex
import jax
import jax.numpy as jnp
from flax import struct

from coherent_jax.exploration.base import OnPolicyStrategy
from coherent_jax.networks import MLP, augment

#: largest w_std / action_std per action dimension that the strategies run with (see
#: `LastLayer.weights`)
MAX_W_STD_RATIO = 10.0


@struct.dataclass
class CoherentHParams:
    """The on-policy chain's sweepable scalars in the train state (fields in sorted order,
    so the flattened leaves are those of the string-keyed dict this replaced).

    Attributes:
      action_std: [p] the fixed action noise Lambda_a^-1/2, or None when it is learned
        (then it is the trainable ``log_action_std`` and no leaf here).
      beta: the chain's mixing coefficient in [0, 1].
    """

    action_std: jax.Array | None
    beta: jax.Array


@struct.dataclass
class CoherentSACHParams:
    """Coherent-SAC's sweepable scalars: the chain's beta and the sigma rule of (4.51)
    (fields in sorted order, the leaves of the string-keyed dict this replaced).

    Attributes:
      beta: the chain's mixing coefficient in [0, 1].
      sigma: the current scale of the weight noise sigma_k.
      sigma_alpha: the rule's factor alpha.
      sigma_delta: the rule's threshold delta.
    """

    beta: jax.Array
    sigma: jax.Array
    sigma_alpha: jax.Array
    sigma_delta: jax.Array


class ChainStrategy(OnPolicyStrategy):
    """What the strategies on the beta-chain share: beta, the initial w_std, the action noise.

    ``action_std`` (Lambda_a^-1/2) is a fixed hyperparameter as in the thesis,
    or learned (``log_action_std`` in the parameters) with ``learn_action_std``.
    """

    def __init__(
        self, action_size: int, beta: float, w_std_init: float, action_std: float, learn_action_std: bool
    ):
        self.action_size = int(action_size)
        self.beta = float(beta)
        self.w_std_init = float(w_std_init)
        self.action_std = float(action_std)
        self.learn_action_std = bool(learn_action_std)

    @staticmethod
    def chain_settings(cfg) -> dict:
        """The constructor's chain arguments as ``cfg`` gives them."""
        return {
            "beta": cfg.coherent.beta,
            "w_std_init": cfg.coherent.w_std_init,
            "action_std": cfg.coherent.action_std,
            "learn_action_std": cfg.coherent.learn_action_std,
        }

    def init_hparams(self) -> CoherentHParams:
        fixed = None if self.learn_action_std else jnp.full((self.action_size,), self.action_std, jnp.float32)
        return CoherentHParams(action_std=fixed, beta=jnp.asarray(self.beta, jnp.float32))

    def _action_std_params(self) -> dict:
        """The trainable action noise: ``log_action_std`` [p] when learned, else nothing."""
        if not self.learn_action_std:
            return {}
        return {"log_action_std": jnp.full((self.action_size,), math.log(self.action_std), jnp.float32)}

    def _action_std(self, params, hparams):
        if self.learn_action_std:
            return jnp.exp(params["log_action_std"])
        return hparams.action_std

    def _chain_metrics(self, w_std: chex.Array, action_std: chex.Array, hparams) -> dict[str, jax.Array]:
        """The logged scalars: the mean weight spread ``w_std`` (a scalar), the mean action
        noise and beta."""
        return {
            "w_std": w_std,
            "action_std": jnp.mean(action_std),
            "beta": jnp.asarray(hparams.beta),
        }


class LastLayer:
    """The policy whose last layer the chain perturbs (thesis §4.1).

    Parameters: the trunk x = f_theta(s) (``"trunk"``), the last layer's mean ``mu``
    [p, q+1] and per-weight ``log_w_std`` [p, q+1] (Lambda^-1/2), bias in the last column.
    """

    def __init__(self, action_size: int, hidden, activation: str, w_std_init: float):
        self.action_size = int(action_size)
        self.feature_size = int(hidden[-1])
        self.trunk = MLP(tuple(hidden), activation)
        self.w_std_init = float(w_std_init)

    def init(self, key: jax.Array, obs_size: int) -> dict:
        """``trunk``, ``mu`` and ``log_w_std`` at initialisation."""
        k_trunk, k_mu = jax.random.split(key)
        p, n = self.action_size, self.feature_size + 1
        # Small initial mean weights (as for a Gaussian policy's last layer), zero bias.
        w = jax.nn.initializers.orthogonal(0.01)(k_mu, (self.feature_size, p), jnp.float32).T
        return {
            "trunk": self.trunk.init(k_trunk, jnp.zeros((1, obs_size))),
            "mu": jnp.concatenate([w, jnp.zeros((p, 1), jnp.float32)], axis=1),
            "log_w_std": jnp.full((p, n), math.log(self.w_std_init), jnp.float32),
        }

    def features(self, params, obs: jax.Array) -> jax.Array:
        """x = f_theta(s), obs [..., o] -> [..., q]."""
        return self.trunk.apply(params["trunk"], obs)

    def weights(self, params, action_std: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(mu [p, q+1], w_std [p, q+1], action_std [p]) as the strategies run with them.

        The covariance-form marginals keep float32 within about 0.005 nats per step only
        while the weights' spread is within `MAX_W_STD_RATIO` of the action noise (beta = 0,
        1000-step segments; at 300 they lose every digit and turn NaN). Beyond it the
        action noise is raised, in collection and in the loss alike, so the process run is
        still the process scored.
        """
        w_std = jnp.exp(params["log_w_std"])
        action_std = jnp.maximum(action_std, jnp.max(w_std, axis=-1) / MAX_W_STD_RATIO)
        return params["mu"], w_std, action_std

    def mean_action(self, params, obs: jax.Array) -> jax.Array:
        """The deterministic action mu xh, obs [..., o] -> [..., p]."""
        return jnp.einsum("pk,...k->...p", params["mu"], augment(self.features(params, obs)))
