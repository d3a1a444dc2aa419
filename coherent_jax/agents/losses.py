"""Pure on-policy losses: GAE, the PPO-Clip and A2C policy objectives, the value loss,
and `onpolicy_loss`, the whole loss of a minibatch of segments.

The terms are elementwise over leading batch axes (time-major ``[T, ...]`` for `gae`)
and return scalars as means, so they can be checked against hand computations.
`onpolicy_loss` combines them in the manner of Brax's ``compute_ppo_loss(params, ...,
data) -> (loss, metrics)``: parameters, hyperparameters and a typed minibatch in,
the scalar to differentiate and its diagnostics out; the strategy and the value
network are static arguments (bind them with ``functools.partial``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import chex
import flax.linen as nn
import jax
import jax.numpy as jnp

from coherent_jax.agents.onpolicy_state import AgentParams, HParams
from coherent_jax.exploration.base import OnPolicyStrategy, Segment


def gae(
    rewards: jax.Array,
    values: jax.Array,
    next_values: jax.Array,
    terminated: jax.Array,
    done: jax.Array,
    gamma: jax.Array | float,
    lam: jax.Array | float,
) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimation (Schulman et al. 2016; thesis eq. 2.30-2.31).

        delta_t = r_t + gamma (1 - terminated_t) V(s'_t) - V(s_t)             (2.31)
        A_t     = delta_t + gamma lambda (1 - done_t) A_{t+1}                   (2.30)

    ``next_values`` is V of the state each step reached (before any auto-reset),
    so a time-limit truncation (done, not terminated) is bootstrapped while the
    advantage recursion still stops at the episode boundary. The segment end
    needs no special case: A_T = 0 and V(s'_{T-1}) is already in delta.

    Args:
      rewards, values, next_values: [T, ...].
      terminated, done: [T, ...] bool.
      gamma, lam: scalars.

    Returns:
      (advantages, value targets = advantages + values), both [T, ...].
    """
    chex.assert_equal_shape([rewards, values, next_values, terminated, done])
    not_term = 1.0 - terminated.astype(values.dtype)
    not_done = 1.0 - done.astype(values.dtype)
    deltas = rewards + gamma * not_term * next_values - values

    def backward(adv_next, inputs):
        delta, cont = inputs
        adv = delta + gamma * lam * cont * adv_next
        return adv, adv

    _, advantages = jax.lax.scan(backward, jnp.zeros_like(deltas[0]), (deltas, not_done), reverse=True)
    return advantages, advantages + values


def discounted_returns(
    running: jax.Array, rewards: jax.Array, done: jax.Array, gamma: jax.Array | float
) -> tuple[jax.Array, jax.Array]:
    """Each env's discounted return so far, G_t = gamma G_{t-1} + r_t, restarting after an
    episode ends (terminated or truncated); what reward scaling takes the variance of.

    Args:
      running: [...] G_{-1}, the value the previous segment ended with (0 after a done).
      rewards, done: [T, ...].
      gamma: scalar.

    Returns:
      (G at the segment's end with the done of its last step applied, i.e. what the next
      segment starts from, and G_t for every step [T, ...]).
    """
    chex.assert_equal_shape([rewards, done])
    chex.assert_equal_shape([running, rewards[0]])

    def forward(g, inputs):
        r, d = inputs
        g = gamma * g + r
        return jnp.where(d, 0.0, g), g

    return jax.lax.scan(forward, running, (rewards, done))


class PolicyLossInfo(NamedTuple):
    """Diagnostics of a policy objective, each a scalar."""

    approx_kl: jax.Array
    clip_fraction: jax.Array


def ppo_clip_loss(
    log_prob: jax.Array, old_log_prob: jax.Array, advantages: jax.Array, clip_eps: jax.Array | float
) -> tuple[jax.Array, PolicyLossInfo]:
    """Negative PPO-Clip surrogate (thesis eq. 2.41; eq. 4.53 for Coherent-PPO).

        r_t  = exp(log pi(a_t|.) - log pi_old(a_t|.))
        L    = -mean_t min(r_t A_t, clip(r_t, 1 - eps, 1 + eps) A_t)

    ``approx_kl`` is the estimator mean((r - 1) - log r) >= 0 of KL(old || new).
    """
    chex.assert_equal_shape([log_prob, old_log_prob, advantages])
    log_ratio = log_prob - old_log_prob
    ratio = jnp.exp(log_ratio)
    surrogate = jnp.minimum(ratio * advantages, jnp.clip(ratio, 1 - clip_eps, 1 + clip_eps) * advantages)
    info = PolicyLossInfo(
        approx_kl=jax.lax.stop_gradient(jnp.mean((ratio - 1.0) - log_ratio)),
        clip_fraction=jax.lax.stop_gradient(jnp.mean(jnp.abs(ratio - 1.0) > clip_eps)),
    )
    return -jnp.mean(surrogate), info


def a2c_loss(
    log_prob: jax.Array, old_log_prob: jax.Array, advantages: jax.Array
) -> tuple[jax.Array, PolicyLossInfo]:
    """Negative vanilla policy-gradient objective (Algorithm 1 step 4; Algorithm 4).

    L = -mean_t log pi(a_t | .) A_t
    """
    chex.assert_equal_shape([log_prob, old_log_prob, advantages])
    log_ratio = jax.lax.stop_gradient(log_prob - old_log_prob)
    info = PolicyLossInfo(
        approx_kl=jnp.mean(jnp.exp(log_ratio) - 1.0 - log_ratio),
        clip_fraction=jnp.zeros((), log_prob.dtype),
    )
    return -jnp.mean(log_prob * advantages), info


def value_loss(values: jax.Array, targets: jax.Array) -> jax.Array:
    """Half mean squared error to the value targets (Algorithm 1 step 5)."""
    chex.assert_equal_shape([values, targets])
    return 0.5 * jnp.mean(jnp.square(values - targets))


def standardize(x: jax.Array, eps: float = 1e-8) -> jax.Array:
    """(x - mean) / (std + eps) over all elements."""
    return (x - x.mean()) / (x.std() + eps)


class SegmentBatch(NamedTuple):
    """A minibatch of m whole env segments in time order, as the on-policy loss reads it.

    Attributes:
      segment: what the strategy scores (`Segment`): observations [T, m, o] (normalised),
        actions [T, m, p], ``first`` [T, m], the strategy's stored per-step noise
        [T, m, ...] and its carry at each segment's start [m, ...].
      behaviour_log_prob: [T, m] log pi_old(a_t | history) of collection.
      advantages: [T, m] GAE advantages.
      targets: [T, m] value targets.
      context: for a strategy with ``history_length = H > 0``, the H steps before each
        segment (`rollout.EpisodeHistory`, observations normalised), [H, m, ...]; else ().
    """

    segment: Segment
    behaviour_log_prob: jax.Array
    advantages: jax.Array
    targets: jax.Array
    context: Any = ()

    def envs(self, index: jax.Array) -> SegmentBatch:
        """The segments of the envs ``index`` [k] (`Segment.envs`; the rest on axis 1)."""
        rest = jax.tree.map(lambda x: x[:, index], self._replace(segment=()))
        return rest._replace(segment=self.segment.envs(index))


def segment_log_prob(strategy: OnPolicyStrategy, policy: Any, hparams: Any, batch: SegmentBatch) -> Any:
    """The strategy's `SegmentLogProb` of each segment of ``batch`` [T, m]: with a context
    (H steps before each segment), of the windows context + segment, last T steps kept."""
    if not batch.context:
        return strategy.batch_log_prob(policy, hparams, batch.segment)
    num_steps = batch.segment.obs.shape[0]
    seg = strategy.batch_log_prob(policy, hparams, batch.segment.after(batch.context))
    return jax.tree.map(lambda v: v[-num_steps:], seg)


def onpolicy_loss(
    params: AgentParams,
    hparams: HParams,
    batch: SegmentBatch,
    *,
    strategy: OnPolicyStrategy,
    value_net: nn.Module,
    clipped: bool,
    normalize_advantages: bool,
    value_in_loss: bool = True,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Policy + value loss of one minibatch of whole segments (Algorithms 1, 2, 4, 5).

        L = L_pi + vf_coef L_V - ent_coef mean_t H_t

    with L_pi the PPO-Clip objective (2.41 / 4.53) if ``clipped`` else A2C's, on the
    strategy's log-probabilities of each stored segment (for coherent: the marginals
    log p(a_t | a_<t, s_<=t), 4.37), and L_V the value loss. Without ``value_in_loss``
    (a value function fitted on its own) L = L_pi - ent_coef mean_t H_t and the value
    network is not evaluated.

    Returns:
      (L, metrics: policy_loss, value_loss (only with ``value_in_loss``), entropy,
      approx_kl, clip_fraction).
    """
    chex.assert_rank([batch.behaviour_log_prob, batch.advantages, batch.targets], 2)
    seg = segment_log_prob(strategy, params.policy, hparams.explore, batch)
    adv = standardize(batch.advantages) if normalize_advantages else batch.advantages
    if clipped:
        pi_loss, info = ppo_clip_loss(seg.log_prob, batch.behaviour_log_prob, adv, hparams.clip_eps)
    else:
        pi_loss, info = a2c_loss(seg.log_prob, batch.behaviour_log_prob, adv)
    entropy = jnp.mean(seg.entropy)
    metrics = {"policy_loss": pi_loss}
    if value_in_loss:
        v_loss = value_loss(value_net.apply(params.value, batch.segment.obs), batch.targets)
        total = pi_loss + hparams.vf_coef * v_loss - hparams.ent_coef * entropy
        metrics["value_loss"] = v_loss
    else:
        total = pi_loss - hparams.ent_coef * entropy
    metrics.update(entropy=entropy, approx_kl=info.approx_kl, clip_fraction=info.clip_fraction)
    return total, metrics
