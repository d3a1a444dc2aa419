"""The two interfaces of exploration: an on-policy strategy and an off-policy behaviour.

An on-policy strategy (`OnPolicyStrategy`, for A2C/PPO) owns the stochastic part of the
policy: given the policy trunk (`coherent_jax.networks.MLP`), it defines the last
layer, how actions are drawn during collection (carrying any per-env noise or belief
state explicitly, as rlax's Ornstein-Uhlenbeck noise does), the log-probability of a
stored segment that the losses differentiate, and the deterministic action used for
evaluation.

An off-policy behaviour (`OffPolicyBehaviour`, for SAC) only shapes how the actor
(`coherent_jax.networks.SquashedGaussianActor`, trained as plain SAC) is perturbed
while collecting, carrying per-env state, and how a noise scale adapts after each
iteration (thesis §4.3). The base class is plain SAC: a = tanh(mean + std xi), nothing
adapts.

Algorithms only call these members, so adding a strategy never touches an algorithm.
Conventions: ``obs`` is already normalised; ``first`` marks the first step of an
episode; collection members work on a batch of envs ``[n, ...]``; `log_prob` works on
ONE env's time segment ``[T, ...]`` (a `Segment`; the caller vmaps over envs).
"""

from __future__ import annotations

import abc
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
from flax import struct

from coherent_jax.networks import HEAD_GAIN, SquashedGaussianActor, squash

Params = Any
Carry = Any


class ActOutput(NamedTuple):
    """Result of one collection step for a batch of envs.

    Attributes:
      action: [n, p] the action taken, before clipping to the action bounds.
      log_prob: [n] log-probability of ``action`` under the behaviour policy, as
        the on-policy ratio needs it (NaN where `score_segment` computes it instead).
      carry: per-env strategy state after this step.
      extras: per-env noise that `log_prob` needs again (leading axis n; the
        rollout stores it per step as ``Transition.extras``), e.g. NoisyNet's noise
        or the sampled coherent chain z_t; ``()`` for strategies that need none.
    """

    action: jax.Array
    log_prob: jax.Array
    carry: Carry
    extras: Any = ()


class Segment(NamedTuple):
    """A stored, time-major segment of steps, as the strategies score it (`log_prob`,
    `batch_log_prob`, `score_segment`).

    With T steps and leading batch axes b (none for one env's segment, [m] for a
    minibatch, [n] for a whole collection):

    Attributes:
      obs: [T, *b, o] normalised observations s_t.
      action: [T, *b, p] actions taken (before clipping to the action bounds).
      first: [T, *b] bool, s_t starts an episode.
      carry0: the strategy's carry at the segment's start (what `init_carry` or the
        previous segment left), leading axes b; ``()`` where the caller has none.
      extras: what `act` returned as `ActOutput.extras` at each step, leading axes
        [T, *b]; ``()`` for strategies that store none.
    """

    obs: jax.Array
    action: jax.Array
    first: jax.Array
    carry0: Any = ()
    extras: Any = ()

    def check(self, batch_rank: int = 0) -> None:
        """Asserts the shapes above for ``batch_rank`` leading batch axes (at trace time)."""
        lead = 1 + batch_rank
        chex.assert_rank([self.obs, self.action, self.first], [lead + 1, lead + 1, lead])
        steps = [self.obs, self.action, self.first, *jax.tree.leaves(self.extras)]
        chex.assert_equal_shape_prefix(steps, lead)

    def after(self, history: Any) -> Segment:
        """The window of the H steps before the segment and the segment, H + T steps.

        ``history`` has fields obs, action, first with leading axes [H, *b]
        (`rollout.EpisodeHistory`); the segment's arrays are cast to its dtypes. Only a
        strategy that stores no extras reads a history.
        """
        if jax.tree.leaves(self.extras):
            raise ValueError("a strategy that reads a history stores no per-step extras")
        join = lambda h, s: jnp.concatenate([h, s.astype(h.dtype)])  # noqa: E731
        return self._replace(
            obs=join(history.obs, self.obs),
            action=join(history.action, self.action),
            first=join(history.first, self.first),
        )

    def envs(self, index: jax.Array) -> Segment:
        """The segments of the envs ``index`` [k] of a batch of segments, each field
        indexed on its `SEGMENT_AXES` axis."""
        pick = {0: lambda x: x[index], 1: lambda x: x[:, index]}
        fields = zip(SEGMENT_AXES, self, strict=True)
        return Segment(*(jax.tree.map(pick[axis], field) for axis, field in fields))


#: the axis of each field of a batch of segments (`Segment` [T, m, ...]) that indexes them
SEGMENT_AXES = Segment(obs=1, action=1, first=1, carry0=0, extras=1)


@struct.dataclass
class NoHParams:
    """The hyperparameters of a strategy that has none a sweep may vary (no leaves).

    A strategy with some declares its own ``flax.struct.dataclass``: one field per
    scalar, in sorted order, read as attributes; a sweep addresses a field by its path
    in the trainer's hyperparameters (e.g. ``explore.beta``, `config.Sweepable`).
    """


class SegmentLogProb(NamedTuple):
    """Per-step log-probabilities and entropies of a stored segment, each [T]."""

    log_prob: jax.Array
    entropy: jax.Array


class OnPolicyStrategy(abc.ABC):
    """A stochastic policy head with its exploration process (A2C/PPO)."""

    name: str = "base"
    #: Steps of each env's past that `log_prob` reads before a segment (coherent's episode
    #: prefix). When it is H > 0 the trainer keeps each env's last H steps (raw observations,
    #: actions, ``first`` flags) and hands `score_segment` and `batch_log_prob` windows of
    #: H + T steps (`Segment.after`), of which only the last T are scored; 0: segments alone.
    history_length: int = 0

    @classmethod
    @abc.abstractmethod
    def from_config(cls, cfg: Any, action_size: int) -> OnPolicyStrategy:
        """The strategy with the settings ``cfg`` gives it, for ``action_size`` actions."""

    @abc.abstractmethod
    def init(self, key: jax.Array, obs_size: int) -> Params:
        """Trainable policy parameters (trunk and head)."""

    def init_hparams(self) -> Any:
        """Non-trainable scalars (e.g. beta) that a vmapped sweep may vary: a
        ``flax.struct.dataclass`` of arrays (`NoHParams` when there are none)."""
        return NoHParams()

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

    def score_segment(
        self, params: Params, hparams: Any, segment: Segment, carry: Carry, log_prob: jax.Array
    ) -> tuple[jax.Array, Carry]:
        """Behaviour log-probabilities of a whole collected segment (``segment`` [T, n, ...]).

        For strategies that score a segment at once rather than step by step in `act`
        (coherent's joint Gaussian); they also finish the carry the next segment starts
        from. ``segment.carry0`` / ``carry`` are the carries at the segment's start / end,
        ``log_prob`` [T, n] what `act` returned. Returns (log_prob [T, n], carry).
        Default: both unchanged.
        """
        del params, hparams, segment
        return log_prob, carry

    def adapt(self, params: Params, hparams: Any, carry: Carry, obs: jax.Array) -> Carry:
        """Adapts the exploration noise after a segment, on its states obs [T, n, o].

        For strategies whose noise scale is not learned (PSNE: eq. 4.51). Returns the
        carry the next segment starts from. Default: unchanged.
        """
        del params, hparams, obs
        return carry

    def batch_log_prob(self, params: Params, hparams: Any, segment: Segment) -> SegmentLogProb:
        """`log_prob` of a minibatch of m segments, ``segment`` [T, m, ...] (``carry0``
        [m, ...]); the result [T, m].

        Default: `log_prob` vmapped over the segments. A strategy overrides it when the
        segments of a minibatch can share work that separate calls would repeat (psne:
        one perturbation per episode rather than per step); the values stay those of
        `log_prob`.
        """
        per_segment = jax.vmap(self.log_prob, in_axes=(None, None, SEGMENT_AXES), out_axes=1)
        return per_segment(params, hparams, segment)

    @abc.abstractmethod
    def log_prob(self, params: Params, hparams: Any, segment: Segment) -> SegmentLogProb:
        """Log-probabilities of one env's segment, ``segment`` [T, ...] (`Segment.check`).

        ``segment.carry0`` is that env's carry as stored at the start of the segment;
        ``segment.extras`` is what `act` returned as `ActOutput.extras` at each step. The
        result is differentiable with respect to ``params``.

        Why stored extras rather than regenerating the noise from keys: the noise of a
        step is a function of every earlier step's key and ``first`` flag (an episode's
        draw, a chain), so regenerating it would repeat the strategy's sampling logic
        inside every loss; a strategy stores what it sampled, or a key that determines
        it when that is smaller (psne), and the algorithms stay strategy-agnostic.
        """

    @abc.abstractmethod
    def mean_action(self, params: Params, obs: jax.Array) -> jax.Array:
        """The deterministic (evaluation) action, obs [..., o] -> [..., p]."""

    def metrics(self, params: Params, hparams: Any) -> dict[str, jax.Array]:
        """Scalars worth logging (e.g. the mean exploration std)."""
        del params, hparams
        return {}


class OffPolicyBehaviour:
    """How SAC's actor explores while collecting; this base class is plain SAC."""

    name: str = "action"
    #: the actor should put LayerNorm between its layers (PSNE).
    actor_layer_norm: bool = False
    #: the orthogonal init gain of the actor's mean head (Lattice starts it larger).
    actor_head_gain: float = HEAD_GAIN

    @classmethod
    def from_config(cls, cfg: Any, action_size: int) -> OffPolicyBehaviour:
        """The behaviour with the settings ``cfg`` gives it (plain SAC has none)."""
        del cfg, action_size
        return cls()

    def init_hparams(self) -> Any:
        """Sweepable scalars of the behaviour (e.g. beta and sigma): a ``flax.struct.dataclass``
        of arrays (`NoHParams` when there are none)."""
        return NoHParams()

    def init_carry(
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

    def act(
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

    def adapt(
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
