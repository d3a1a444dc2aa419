"""Pure losses of Soft Actor-Critic (thesis §2.4.3, Algorithm 3), on a typed replay batch.

Each takes the parameters it differentiates first, then the other inputs and a replay
minibatch (`coherent_jax.agents.replay.Experience`, observations normalised), and returns
(loss, aux) so that ``jax.value_and_grad(..., has_aux=True)`` applies directly:

    y = r + gamma (1 - d) (min_i Q_targ,i(s', a') - alpha log pi(a'|s')),  a' ~ pi(.|s')   (2.47)
    L(phi_i) = E[(Q_phi_i(s, a) - y)^2]                                             (2.46)
    J(theta) = E[min_i Q_phi_i(s, a~) - alpha log pi(a~|s)],  a~ = tanh(mu + sigma xi)  (2.50, 2.51)
    L(log alpha) = -E[log alpha (log pi(a~|s) + target_entropy)]       (Haarnoja et al. 2018b)

The networks (`SquashedGaussianActor`, the twin `QNetwork`) are static arguments.
"""

from __future__ import annotations

from typing import Any

import chex
import flax.linen as nn
import jax
import jax.numpy as jnp

from coherent_jax.agents.replay import Experience
from coherent_jax.networks import SquashedGaussianActor, squash


def q_values(critic: nn.Module, critic_params: Any, obs: jax.Array, action: jax.Array) -> jax.Array:
    """Both critics' Q(s, a), [2, B] (parameters stacked on a leading axis of size 2)."""
    return jax.vmap(critic.apply, in_axes=(0, None, None))(critic_params, obs, action)


def soft_target(
    reward: jax.Array,
    terminated: jax.Array,
    next_q: jax.Array,
    next_log_prob: jax.Array,
    gamma: jax.Array,
    alpha: jax.Array,
) -> jax.Array:
    """y = r + gamma (1 - d) (min_i Q_targ,i(s', a') - alpha log pi(a'|s')) (2.47).

    Args:
      reward, terminated, next_log_prob: [B].
      next_q: [2, B] target Q-values of the twin critics at (s', a').
    """
    chex.assert_rank([reward, terminated, next_log_prob, next_q], [1, 1, 1, 2])
    soft_value = jnp.min(next_q, axis=0) - alpha * next_log_prob
    return reward + gamma * (1.0 - terminated) * soft_value


def critic_target(
    actor_params: Any,
    target_critic_params: Any,
    batch: Experience,
    key: jax.Array,
    gamma: jax.Array,
    alpha: jax.Array,
    *,
    actor: SquashedGaussianActor,
    critic: nn.Module,
) -> jax.Array:
    """The regression target y of (2.47), [B], with a' ~ pi(.|s') drawn from ``key``; no gradient."""
    next_action, next_log_prob = squash(key, actor.dist(actor_params, batch.next_obs))
    next_q = q_values(critic, target_critic_params, batch.next_obs, next_action)
    return jax.lax.stop_gradient(
        soft_target(batch.reward, batch.terminated, next_q, next_log_prob, gamma, alpha)
    )


def critic_loss(
    critic_params: Any, batch: Experience, target: jax.Array, *, critic: nn.Module
) -> tuple[jax.Array, jax.Array]:
    """(2.46) summed over the twin critics; aux: Q(s, a) [2, B]."""
    q = q_values(critic, critic_params, batch.obs, batch.action)
    return jnp.sum(jnp.mean(jnp.square(q - target[None]), axis=1)), q


def actor_loss(
    actor_params: Any,
    critic_params: Any,
    batch: Experience,
    key: jax.Array,
    alpha: jax.Array,
    *,
    actor: SquashedGaussianActor,
    critic: nn.Module,
) -> tuple[jax.Array, jax.Array]:
    """-J(theta) of (2.51) with a~ = tanh(mu + sigma xi) drawn from ``key``; aux: log pi(a~|s) [B]."""
    action, log_prob = squash(key, actor.dist(actor_params, batch.obs))
    q_pi = jnp.min(q_values(critic, critic_params, batch.obs, action), axis=0)
    return jnp.mean(alpha * log_prob - q_pi), log_prob


def temperature_loss(log_alpha: jax.Array, log_prob: jax.Array, target_entropy: jax.Array) -> jax.Array:
    """-E[log alpha (log pi(a~|s) + target_entropy)]: alpha grows while the entropy is below target."""
    gap = jax.lax.stop_gradient(log_prob + target_entropy)
    return -jnp.mean(log_alpha * gap)
