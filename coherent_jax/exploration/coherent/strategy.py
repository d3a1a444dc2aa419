"""The coherent strategies: Coherent-A2C/PPO (Algorithms 4 and 5) and Coherent-SAC's behaviour.

Deep Coherent Exploration perturbs only the policy's last layer with the beta-chain
(thesis §4.1, eqs. 4.1-4.5); on-policy, every action is scored with the analytic
marginal log p(a_t | a_<t, s_<=t) of the chain actually run (§4.2): by the filter of
`filter`, the joint form of `joint`, or the chained blocks of `exact` (modules of this
folder) for long segments and episode prefixes. docs/coherent.md lists the
options and what each runs.
"""

from __future__ import annotations

from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp

from coherent_jax.exploration.adaptive import SigmaRule, adapt_sigma, policy_distance
from coherent_jax.exploration.base import SEGMENT_AXES, ActOutput, OffPolicyBehaviour, SegmentLogProb
from coherent_jax.exploration.chain import ChainParams, chain_params, chain_step
from coherent_jax.exploration.coherent.exact import MAX_BLOCK, block_size, chained_marginals
from coherent_jax.exploration.coherent.filter import (
    Belief,
    filter_step,
    predictive_entropy,
    prior_belief,
    segment_marginals,
)
from coherent_jax.exploration.coherent.joint import segment_marginals_joint
from coherent_jax.exploration.coherent.layer import ChainStrategy, CoherentSACHParams, LastLayer
from coherent_jax.networks import augment, squash
from coherent_jax.sweep_axis import least_point

# --------------------------------------------------------------------------------------
# The strategy: Coherent-A2C / Coherent-PPO (Algorithms 4 and 5).


class CoherentCarry(NamedTuple):
    """Per-env state of the coherent strategy, in standardised coordinates.

    The chain and the belief are stored for ``z = (w - mu) / w_std`` rather than for
    w itself. Under fixed parameters this is the same chain (w_t = mu + w_std z_t and
    z_t = (1 - beta) z_{t-1} + sqrt(2 beta - beta^2) eps, eqs. 4.1-4.4) and the same
    belief. When an update changes mu or w_std mid-episode, the exploring policy
    follows the new mean instead of keeping weights drawn around the old one (at
    beta = 0 it would otherwise never see the update until the episode ends), and
    the stored belief maps onto the new parameters, so the loss's segment start is a
    differentiable function of mu and w_std.

    Attributes:
      z: [p, q+1] standardised weights z_{t-1} used at the previous step.
      mean: [p, q+1] mean of alpha(z_t), the belief before a_t ([p, 0] where the
        strategy keeps no belief, see `CoherentExploration._keeps_belief`).
      cov: [p, q+1, q+1] covariance of alpha(z_t) ([p, 0, 0] likewise).
      restart: bool, the chain starts afresh at the next step even if its episode
        goes on (``gradient="exact"``: set at the end of every segment).
    """

    z: chex.Array
    mean: chex.Array
    cov: chex.Array
    restart: chex.Array


def _to_weights(carry: CoherentCarry, mu: chex.Array, w_std: chex.Array) -> Belief:
    """alpha(w) from alpha(z): mean mu + w_std m_z, cov diag(w_std_i) P_z diag(w_std_i)."""
    return Belief(
        mean=mu + w_std * carry.mean,
        cov=w_std[:, :, None] * carry.cov * w_std[:, None, :],
    )


def _to_standard(belief: Belief, mu: chex.Array, w_std: chex.Array) -> tuple[chex.Array, chex.Array]:
    return (belief.mean - mu) / w_std, belief.cov / (w_std[:, :, None] * w_std[:, None, :])


def episode_history_length(episode_length: int, unroll_length: int) -> int:
    """Prefix steps a segment's window needs so that it reaches back to the segment's
    episode start: at least ``episode_length - 1`` (a segment may start at the episode's
    last step), rounded up to whole segments so that the window's blocks line up with
    the segment's (``coherent.gradient=episode``)."""
    if episode_length < 1 or unroll_length < 1:
        raise ValueError(f"episode and unroll lengths must be >= 1, got {episode_length}, {unroll_length}")
    return -(-(episode_length - 1) // unroll_length) * unroll_length


def window_start_block(first: chex.Array, history_length: int, block: int) -> chex.Array:
    """The first block of episode-mode windows that their segments' scores depend on.

    A window holds `history_length` prefix steps, then the segment; every kept step
    conditions on its episode from that episode's start on, and the latest start at or
    before the segment's first step (window index H; index 0 if none) is the earliest
    any of them needs. The block holding it, at its earliest over the windows (``first``
    [W, *b]) and over a sweep's points, so that one ``lax.cond`` per block skips the
    blocks before it for the whole minibatch (`exact.chained_marginals`).
    """
    if first.shape[0] <= history_length:  # a segment without its prefix: nothing to skip
        return jnp.zeros((), jnp.int32)
    first = jnp.asarray(first, bool)[: history_length + 1]
    step = jnp.arange(history_length + 1).reshape((-1,) + (1,) * (first.ndim - 1))
    starts = jnp.max(jnp.where(first, step, 0), axis=0)
    return least_point(jnp.min(starts) // block)


class CoherentExploration(ChainStrategy):
    """Deep Coherent Exploration of the policy's last layer (thesis §4.1-4.2).

    Parameters: the trunk f_theta, the last-layer mean ``mu`` [p, q+1] and per-weight
    ``log_w_std`` [p, q+1] (Lambda^-1/2) of its policy (`layer.LastLayer`,
    ``layer``), and ``log_action_std`` [p] when learned
    (otherwise ``action_std`` is a fixed, sweepable hyperparameter, as in the
    thesis). ``beta`` is a hyperparameter (an array, so it can be swept).

    Collection samples w_t from the chain and a_t ~ N(w_t xh_t, action_std^2)
    (Algorithm 5, steps 4-8). The behaviour log-probabilities are the analytic
    marginals (steps 12-14): with ``inference="joint"`` (default) `score_segment`
    scores the whole segment at once from its joint Gaussian and stores the belief
    that starts the next one; with ``"filter"`` `act` runs the filter step by step.
    `log_prob` recomputes the marginals of a stored segment under the current
    parameters in the same form; segments longer than `exact.MAX_BLOCK` are
    scored as blocks of the joint form chained by differentiable beliefs.

    ``gradient`` chooses what a segment's first step conditions on:

    * ``"exact"`` (default): the chain restarts at the first step of every segment,
      as Algorithm 5 samples w_0 at t = 0 of every buffer (steps 4-5), besides every
      episode start. Every segment is then scored from the prior, each log p(a_t | ...)
      conditions on all that the chain has seen, re-inferred under the current
      parameters, and the loss's gradient is the thesis's estimator (4.14) of the
      process actually run. The chain's correlations span at most ``unroll_length``
      steps: ``unroll_length = episode_length`` keeps them over whole episodes.
    * ``"episode"``: the chain runs on across segments within an episode, and the loss
      re-infers each segment's episode prefix under the current parameters: the trainer
      keeps each env's last `history_length` steps (at least ``episode_length - 1``)
      and `log_prob` scores the window prefix + segment from the prior at its first
      step, every episode start inside it resetting the belief (4.33). The segment's
      log-probabilities are then the thesis's marginals (4.37)/(4.49) of the episode
      filtered from its start, and their gradient the thesis's estimator (4.14) for
      the chain actually run, at a cost that grows with the prefix.
    * ``"stored"``: the chain runs on across segments, and a segment that starts
      mid-episode starts from the belief stored when it was collected, a constant of
      the data mapped onto the current mu and w_std: the right values (the ratio is 1
      at the collection parameters) but not the thesis's gradient (see
      ``python -m benchmarks gradient``). Kept for the ablation.

    ``episode_restart=False`` lets the chain run across episode starts; only the
    segment starts of ``"exact"`` restart it then, which is Algorithm 5's buffer: w_0
    drawn at t = 0, w_t ~ p(w_t | w_t-1) at every later step, across env resets.
    """

    name = "coherent"

    def __init__(
        self,
        action_size: int,
        hidden,
        activation: str,
        beta: float,
        w_std_init: float,
        action_std: float,
        learn_action_std: bool = False,
        remat: bool = False,
        inference: str = "joint",
        gradient: str = "exact",
        episode_restart: bool = True,
        episode_length: int = 0,
        unroll_length: int = 0,
    ):
        if inference not in ("joint", "filter"):
            raise ValueError(f"inference must be 'joint' or 'filter', got {inference!r}")
        if gradient not in ("exact", "stored", "episode"):
            raise ValueError(f"gradient must be 'exact', 'stored' or 'episode', got {gradient!r}")
        if gradient == "episode" and (inference != "joint" or not episode_restart or unroll_length < 1):
            raise ValueError("gradient='episode' needs inference='joint', episode_restart and unroll_length")
        super().__init__(action_size, beta, w_std_init, action_std, learn_action_std)
        self.layer = LastLayer(action_size, hidden, activation, w_std_init)
        self.remat = bool(remat)
        self.inference = inference
        self.gradient = gradient
        self.episode_restart = bool(episode_restart)
        if gradient == "episode":
            self.history_length = episode_history_length(episode_length, unroll_length)
            self.block = block_size(int(unroll_length))

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(
            action_size,
            cfg.policy_hidden,
            cfg.activation,
            **cls.chain_settings(cfg),
            remat=cfg.coherent.remat,
            inference=cfg.coherent.inference,
            gradient=cfg.coherent.gradient,
            episode_restart=cfg.coherent.episode_restart,
            episode_length=cfg.episode_length,
            unroll_length=cfg.unroll_length,
        )

    # ---------------------------------------------------------------- params
    def init(self, key, obs_size):
        return {**self.layer.init(key, obs_size), **self._action_std_params()}

    def _head(self, params, hparams):
        """(mu, w_std, action_std) of the last layer (`LastLayer.weights`)."""
        return self.layer.weights(params, self._action_std(params, hparams))

    def _chain(self, params, hparams) -> ChainParams:
        """The chain's parameters: the last layer's (`_head`) and ``hparams.beta``."""
        return chain_params(*self._head(params, hparams), hparams.beta)

    @property
    def _keeps_belief(self) -> bool:
        """Whether the carry holds a belief: not when every segment is scored at once from
        the prior or the episode's start (``inference="joint"``, ``gradient="exact"`` or
        ``"episode"``). The belief is then empty
        ([n, p, 0] and [n, p, 0, 0]) instead of p (q+1)^2 floats per env that the
        rollout's loop would carry and the loss would gather for nothing (at the
        defaults, 6.5 MB per rollout step with 64 envs)."""
        return not (self.inference == "joint" and self.gradient in ("exact", "episode"))

    def _segment_belief(self, carry0: CoherentCarry, mu: chex.Array, w_std: chex.Array) -> Belief:
        """The belief a segment starts from: the stored one in weight coordinates, or the
        prior where the carry holds none (the segment restarts the chain)."""
        if self._keeps_belief:
            return _to_weights(carry0, mu, w_std)
        return prior_belief(mu, w_std)

    def init_carry(self, key, params, hparams, num_envs):
        p, n = self.action_size, self.layer.feature_size + 1
        m = n if self._keeps_belief else 0
        return CoherentCarry(
            z=jnp.zeros((num_envs, p, n), jnp.float32),
            mean=jnp.zeros((num_envs, p, m), jnp.float32),
            cov=jnp.broadcast_to(jnp.eye(m, dtype=jnp.float32), (num_envs, p, m, m)),
            # The chain starts at the first step of training whatever ``first`` says there.
            restart=jnp.ones((num_envs,), bool),
        )

    # ------------------------------------------------------------ collection
    def act(self, key, params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        chain = self._chain(params, hparams)
        mu, w_std, action_std, beta = chain
        x = self.layer.features(params, obs)  # [n, q]
        num_envs = x.shape[0]
        k_w, k_a = jax.random.split(key)
        # The chain in standard coordinates; a fresh draw at an episode start or a restart.
        first = jnp.logical_or(self._chain_first(first), carry.restart)
        z = chain_step(k_w, carry.z, first, beta)
        carry = carry._replace(restart=jnp.zeros_like(carry.restart))
        w = mu + w_std * z  # [n, p, q+1]
        xh = augment(x)
        mean_action = jnp.einsum("npk,nk->np", w, xh)
        action = mean_action + action_std * jax.random.normal(k_a, mean_action.shape, mean_action.dtype)

        if self.inference == "joint":
            # The segment is scored at once in `score_segment`; only the chain moves here.
            logp = jnp.full((num_envs,), jnp.nan, action.dtype)
            return ActOutput(action, logp, carry._replace(z=z))

        def filt(c, x_e, a_e, f_e):
            belief, logp = filter_step(_to_weights(c, mu, w_std), x_e, a_e, f_e, chain)
            return _to_standard(belief, mu, w_std), logp

        (mean, cov), logp = jax.vmap(filt)(carry, x, action, first)
        chex.assert_shape(logp, (num_envs,))
        return ActOutput(action, logp, carry._replace(z=z, mean=mean, cov=cov))

    def _chain_first(self, first: chex.Array) -> chex.Array:
        """Where episode starts restart the chain: every ``first``, or none with
        ``episode_restart=False`` (the chain then runs across resets, as through the
        thesis's buffer; only the strategy's own restarts start it afresh)."""
        return first if self.episode_restart else jnp.zeros_like(first)

    def _segment_first(self, first: chex.Array, restart: chex.Array) -> chex.Array:
        """Where the chain starts afresh in a segment: its episode starts (unless
        ``episode_restart`` is off), and its first step if the chain restarted there."""
        first = self._chain_first(first)
        return first.at[0].set(jnp.logical_or(first[0], restart))

    def _score(self, belief0, x, a, first, chain: ChainParams):
        """The segment's marginals in the configured form; (logp, end belief, variances)."""
        if self.inference == "filter":
            return segment_marginals(belief0, x, a, first, chain, remat=self.remat)
        # With the exact gradient every segment starts the chain: the stored belief's
        # terms are zero and need not be formed.
        from_prior = self.gradient == "exact"
        if x.shape[0] > MAX_BLOCK:
            return chained_marginals(belief0, x, a, first, chain, from_prior=from_prior, remat=self.remat)
        return segment_marginals_joint(belief0, x, a, first, chain, from_prior)

    def score_segment(self, params, hparams, segment, carry, log_prob):
        segment.check(batch_rank=1)
        # With the exact gradient the next segment restarts the chain (Algorithm 5, steps 4-5).
        carry = carry._replace(restart=jnp.full_like(carry.restart, self.gradient == "exact"))
        if self.gradient == "episode":  # windows of prefix + segment, scored as the loss scores them
            return self.batch_log_prob(params, hparams, segment).log_prob, carry
        if self.inference == "filter":
            return log_prob, carry  # scored step by step in `act`
        chain = self._chain(params, hparams)
        mu, w_std = chain.mu, chain.w_std
        x = self.layer.features(params, segment.obs)  # [T, n, q]

        def score(c0, x_e, a_e, f_e):
            f_e = self._segment_first(f_e, c0.restart)
            logp, belief, _ = self._score(self._segment_belief(c0, mu, w_std), x_e, a_e, f_e, chain)
            return logp, _to_standard(belief, mu, w_std)

        logp, (mean, cov) = jax.vmap(score, in_axes=(0, 1, 1, 1), out_axes=(1, 0))(
            segment.carry0, x, segment.action, segment.first
        )
        if self.gradient == "exact":
            return logp, carry  # the next segment starts from the prior: no belief to keep
        return logp, carry._replace(mean=mean, cov=cov)

    # ------------------------------------------------------------------ loss
    def log_prob(self, params, hparams, segment, start_block=None):
        """`OnPolicyStrategy.log_prob`; with ``gradient="episode"``, of one window, its blocks
        before ``start_block`` skipped (default: its own `window_start_block`)."""
        segment.check()
        actions = segment.action
        chain = self._chain(params, hparams)
        x = self.layer.features(params, segment.obs)
        if self.gradient == "episode":
            if start_block is None:
                start_block = window_start_block(segment.first, self.history_length, self.block)
            return self._window_log_prob(x, actions, segment.first, chain, start_block)
        # The stored belief is a constant of the data (like a stored RNN state); its
        # mapping onto the current mu and w_std is not.
        # With gradient="exact" a segment's chain starts at its first step, so the
        # stored belief is never used and nothing is held constant.
        carry0 = jax.tree.map(jax.lax.stop_gradient, segment.carry0)
        first = self._segment_first(segment.first, carry0.restart)
        belief0 = self._segment_belief(carry0, chain.mu, chain.w_std)
        logp, _, pred_var = self._score(belief0, x, actions, first, chain)
        return SegmentLogProb(logp, predictive_entropy(pred_var))

    def batch_log_prob(self, params, hparams, segment):
        if self.gradient != "episode":
            return super().batch_log_prob(params, hparams, segment)
        # One start block for the minibatch: the blocks before every window's episode start are skipped.
        start = window_start_block(segment.first, self.history_length, self.block)
        per_segment = jax.vmap(self.log_prob, in_axes=(None, None, SEGMENT_AXES, None), out_axes=1)
        return per_segment(params, hparams, segment, start)

    def _window_log_prob(self, x, actions, first, chain: ChainParams, start) -> SegmentLogProb:
        """``gradient="episode"``: a window of `history_length` prefix steps and a segment,
        scored from the prior at its first step as blocks of the joint form chained by
        differentiable beliefs (`exact.chained_marginals`). The window always
        reaches back to the segment's episode start, which resets the belief there (4.33);
        the blocks before ``start`` (`window_start_block`) are skipped, as nothing kept
        depends on them. The trainer reads the last T steps."""
        first = jnp.asarray(first, bool).at[0].set(True)
        prior = prior_belief(chain.mu, chain.w_std)
        logp, _, pred_var = chained_marginals(
            prior,
            x,
            actions,
            first,
            chain,
            self.block,
            from_prior=True,
            remat=self.remat,
            start_block=start,
        )
        return SegmentLogProb(logp, predictive_entropy(pred_var))

    def mean_action(self, params, obs):
        return self.layer.mean_action(params, obs)

    def metrics(self, params, hparams):
        _, w_std, action_std = self._head(params, hparams)
        return self._chain_metrics(jnp.mean(w_std), action_std, hparams)


# --------------------------------------------------------------------------------------
# Coherent-SAC (thesis §4.3 and §4.4.3).


class CoherentBehaviour(OffPolicyBehaviour):
    """The SAC actor's mean head [p, q+1] follows the beta-chain around its learned value.

    One scale instead of per-weight w_std: W_t = W + sigma z_t, with z_t the
    standardised chain (4.1-4.5), and sigma adapts by (4.50)-(4.51), set by the
    ``coherent_sac.*`` settings. The actor itself trains as plain SAC.
    """

    name = "coherent"

    def __init__(self, beta: float, rule: SigmaRule):
        self.beta = float(beta)
        self.rule = rule

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(cfg.coherent.beta, SigmaRule.from_options(cfg.coherent_sac))

    def init_hparams(self) -> CoherentSACHParams:
        rule = self.rule.hparams()
        return CoherentSACHParams(
            beta=jnp.asarray(self.beta, jnp.float32),
            sigma=rule.sigma,
            sigma_alpha=rule.sigma_alpha,
            sigma_delta=rule.sigma_delta,
        )

    def init_carry(self, key, actor, actor_params, hparams, num_envs):
        # z_0 ~ N(0, I) for every env; `first` at the first step redraws it anyway.
        return jax.random.normal(key, (num_envs,) + actor_params["mu"].shape, jnp.float32)

    def act(self, key, actor, actor_params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        chex.assert_shape(carry, (obs.shape[0],) + actor_params["mu"].shape)
        # ``key`` draws xi exactly as plain SAC does, so sigma = 0 reproduces its actions.
        k_z, k_a = jax.random.fold_in(key, 1), key
        z = chain_step(k_z, carry, first, hparams.beta)
        x = actor.features(actor_params, obs)
        # (mu + sigma z_t) xh = mu xh + sigma z_t xh: the first term is the unperturbed
        # actor's, computed the same way, so sigma = 0 gives its actions bit for bit.
        dist = actor.dist_from_features(actor_params, x)
        dist = dist._replace(mean=dist.mean + hparams.sigma * jnp.einsum("npk,nk->np", z, augment(x)))
        action, _ = squash(k_a, dist)
        return action, z

    def adapt(self, key, actor, actor_params, hparams, obs):
        chex.assert_rank(obs, 2)
        x = actor.features(actor_params, obs)
        # One perturbed actor: a draw from the chain's stationary law N(mu, sigma^2 I).
        z = jax.random.normal(key, actor_params["mu"].shape, actor_params["mu"].dtype)
        pre = actor.dist_from_features(actor_params, x).mean
        mean = jnp.tanh(pre)
        perturbed = jnp.tanh(pre + hparams.sigma * jnp.einsum("pk,nk->np", z, augment(x)))
        distance = policy_distance(mean, perturbed)
        sigma = adapt_sigma(hparams.sigma, distance, hparams.sigma_delta, hparams.sigma_alpha)
        metrics = {"sigma": hparams.sigma, "policy_distance": distance, "beta": hparams.beta}
        return hparams.replace(sigma=sigma), metrics
