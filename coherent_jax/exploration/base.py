"""The interface every exploration strategy implements.

A strategy owns the stochastic part of the policy: given the policy trunk
(`coherent_jax.networks.MLP`), it defines the last layer, how actions are drawn
during collection (carrying any per-env noise or belief state explicitly, as
rlax's Ornstein-Uhlenbeck noise does), the log-probability of a stored segment
that on-policy losses differentiate, and the deterministic action used for
evaluation. Algorithms only call these methods, so adding a strategy never
touches an algorithm.

Conventions: ``obs`` is already normalised; ``first`` marks the first step of an
episode; collection methods work on a batch of envs ``[n, ...]``; `log_prob`
works on ONE env's time segment ``[T, ...]`` (the caller vmaps over envs).

Off-policy algorithms (SAC) own their actor (`coherent_jax.networks.SquashedGaussianActor`)
and train it as usual; a strategy only shapes *behaviour* there, through the
``offpolicy_*`` hooks: how a collection step perturbs the actor (carrying per-env
state), and how a noise scale adapts after each iteration (thesis §4.3). The
defaults are plain SAC: sample a = tanh(mean + std xi) and adapt nothing.
"""

from __future__ import annotations

import abc
from typing import Any, NamedTuple

import jax

from coherent_jax.networks import SquashedGaussianActor, squash

Params = Any
Carry = Any


class ActOutput(NamedTuple):
    """Result of one collection step for a batch of envs.

    Attributes:
      action: [n, p] the action taken, before clipping to the action bounds.
      log_prob: [n] log-probability of ``action`` under the behaviour policy, as
        the on-policy ratio needs it (for coherent: the filter's marginal).
      carry: per-env strategy state after this step.
      extras: per-env noise that `log_prob` needs again (leading axis n; the
        rollout stores it per step as ``Transition.extras``), e.g. NoisyNet's noise
        or the sampled coherent chain z_t; ``()`` for strategies that need none.
    """

    action: jax.Array
    log_prob: jax.Array
    carry: Carry
    extras: Any = ()


class SegmentLogProb(NamedTuple):
    """Per-step log-probabilities and entropies of a stored segment, each [T]."""

    log_prob: jax.Array
    entropy: jax.Array


class Exploration(abc.ABC):
    """A stochastic policy head with its exploration process."""

    name: str = "base"

    @abc.abstractmethod
    def init(self, key: jax.Array, obs_size: int) -> Params:
        """Trainable policy parameters (trunk and head)."""

    def init_hparams(self) -> dict[str, jax.Array]:
        """Non-trainable scalars (e.g. beta) that a vmapped sweep may vary."""
        return {}

    def init_carry(self, key: jax.Array, params: Params, hparams: Any, num_envs: int) -> Carry:
        """Per-env state at the start of training (leading axis num_envs)."""
        del key, params, hparams, num_envs
        return ()

    @abc.abstractmethod
    def act(
        self,
        key: jax.Array,
        params: Params,
        hparams: Any,
        carry: Carry,
        obs: jax.Array,
        first: jax.Array,
    ) -> ActOutput:
        """Draws actions for a batch of envs, obs [n, o], first [n]."""

    @abc.abstractmethod
    def log_prob(
        self,
        params: Params,
        hparams: Any,
        carry0: Carry,
        obs: jax.Array,
        actions: jax.Array,
        first: jax.Array,
        extras: Any = (),
    ) -> SegmentLogProb:
        """Log-probabilities of one env's segment, obs [T, o], actions [T, p].

        ``carry0`` is that env's carry as stored at the start of the segment;
        ``extras`` is what `act` returned as `ActOutput.extras` at each step (leading
        axis T). The result is differentiable with respect to ``params``.

        Why stored extras rather than regenerating the noise from keys: the noise of a
        step is a function of every earlier step's key and ``first`` flag (an episode's
        draw, a chain), so regenerating it would repeat the strategy's sampling logic
        inside every loss; a strategy stores what it sampled, or a key that determines
        it when that is smaller (psne), and the algorithms stay strategy-agnostic.
        """

    def end_segment(
        self,
        params: Params,
        hparams: Any,
        carry0: Carry,
        carry: Carry,
        data_obs: jax.Array,
        data_actions: jax.Array,
        data_first: jax.Array,
        data_log_prob: jax.Array,
    ) -> tuple[jax.Array, Carry]:
        """Called once per collected segment (time-major [T, n, ...], obs normalised).

        May compute the behaviour log-probabilities of the whole segment at once
        instead of step by step in `act`, and finish the carry that the next segment
        starts from. Returns (log_prob [T, n], carry). Default: both unchanged.
        """
        del params, hparams, carry0, data_obs, data_actions, data_first
        return data_log_prob, carry

    @abc.abstractmethod
    def mean_action(self, params: Params, obs: jax.Array) -> jax.Array:
        """The deterministic (evaluation) action, obs [..., o] -> [..., p]."""

    def metrics(self, params: Params, hparams: Any) -> dict[str, jax.Array]:
        """Scalars worth logging (e.g. the mean exploration std)."""
        del params, hparams
        return {}

    # ------------------------------------------------------ off-policy (SAC)
    #: the off-policy actor should put LayerNorm between its layers (PSNE).
    actor_layer_norm: bool = False

    def offpolicy_init_hparams(self) -> dict[str, jax.Array]:
        """Sweepable scalars of the off-policy behaviour (e.g. beta and sigma)."""
        return {}

    def offpolicy_init_carry(
        self,
        key: jax.Array,
        actor: SquashedGaussianActor,
        actor_params: Params,
        hparams: Any,
        num_envs: int,
    ) -> Carry:
        """Per-env behaviour state at the start of training (leading axis num_envs)."""
        del key, actor, actor_params, hparams, num_envs
        return ()

    def offpolicy_act(
        self,
        key: jax.Array,
        actor: SquashedGaussianActor,
        actor_params: Params,
        hparams: Any,
        carry: Carry,
        obs: jax.Array,
        first: jax.Array,
    ) -> tuple[jax.Array, Carry]:
        """Behaviour actions in [-1, 1] for a batch of envs, obs [n, o], first [n].

        Default: SAC's own sample a = tanh(mean(s) + std(s) xi) (eq. 2.50).
        """
        del first
        action, _ = squash(key, actor.dist(actor_params, obs))
        return action, carry

    def offpolicy_adapt(
        self,
        key: jax.Array,
        actor: SquashedGaussianActor,
        actor_params: Params,
        hparams: Any,
        obs: jax.Array,
    ) -> tuple[Any, dict[str, jax.Array]]:
        """Called after each iteration's updates with a replay batch of states
        ``obs`` [B, o]; returns new hparams (e.g. sigma by eq. 4.51) and metrics."""
        del key, actor, actor_params, obs
        return hparams, {}
