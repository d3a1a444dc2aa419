"""Parameter space noise for exploration, PSNE (Plappert et al. 2018).

Every layer's weights and biases are perturbed with one scalar scale sigma,

    theta~ = theta + sigma eps,   eps ~ N(0, I),                  (Plappert et al. §3)

drawn at each episode start and held for the episode; LayerNorm between the policy's
layers (its gain and offset are not perturbed) gives every layer a similar
sensitivity to the same sigma (thesis §4.1.2). sigma is not learned: after every
collected segment it adapts by how much of the noise shows in action space, the
distance (4.50) between the mean actions of the unperturbed and the perturbed policy,
and the rule (4.51) (`coherent_jax.exploration.adaptive`).

A2C/PPO: the policy stays Gaussian, a ~ N(f_theta~(s), std^2) with a learned
state-independent std, and the loss uses the single-sample estimate (4.8): the
log-probability under the perturbed network of collection. The perturbation is
stored as the key it was drawn from (two integers per step instead of one float per
weight) and regenerated in the loss, once per episode of a minibatch
(`batch_log_prob`); sigma lives in the carry (one copy per env), so the loss of a
segment uses the sigma of its collection, and `ParameterNoise.adapt` adapts it on the
segment's states, using each env's current perturbation.

SAC (`PsneBehaviour`): the actor is built with LayerNorm (``actor_layer_norm``);
behaviour perturbs its trunk and mean head (not the log-std head) with sigma per episode and samples
tanh(mean~ + std xi); `PsneBehaviour.adapt` applies (4.50)-(4.51) on a replay batch.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
from flax import traverse_util

from coherent_jax.exploration.action import gaussian_entropy, gaussian_log_prob
from coherent_jax.exploration.adaptive import SigmaHParams, SigmaRule, adapt_sigma, policy_distance
from coherent_jax.exploration.base import ActOutput, OffPolicyBehaviour, OnPolicyStrategy, SegmentLogProb
from coherent_jax.networks import MeanHead, squash
from coherent_jax.sweep_axis import all_points, any_point


def _noisy_paths(flat: dict, skip) -> list:
    """The perturbed leaves' paths, sorted: every leaf whose path names no module in ``skip``."""
    return [p for p in sorted(flat) if not any(s in str(part) for part in p for s in skip)]


def perturbation(params, key: chex.PRNGKey, skip=("LayerNorm",)) -> jax.Array:
    """eps ~ N(0, I) for every perturbed leaf of ``params``, flat [P]: one draw from ``key``,
    laid out leaf by leaf in sorted path order, so the same key always gives the same
    perturbation. (One draw rather than one per leaf: the same distribution, and one
    random-number program per call site instead of one per leaf, which is most of the
    compile time of PSNE's iteration.)"""
    flat = traverse_util.flatten_dict(params)
    paths = _noisy_paths(flat, skip)
    dtype = flat[paths[0]].dtype if paths else jnp.float32
    return jax.random.normal(key, (sum(flat[p].size for p in paths),), dtype)


def apply_perturbation(params, eps: jax.Array, sigma: chex.Array, skip=("LayerNorm",)):
    """theta + sigma eps, eps [P] laid out as by `perturbation`; skipped leaves unchanged."""
    flat = traverse_util.flatten_dict(params)
    out = dict(flat)
    offset = 0
    for path in _noisy_paths(flat, skip):
        leaf = flat[path]
        out[path] = leaf + sigma * eps[offset : offset + leaf.size].reshape(leaf.shape)
        offset += leaf.size
    chex.assert_shape(eps, (offset,))
    return traverse_util.unflatten_dict(out)


def perturb(params, key: chex.PRNGKey, sigma: chex.Array, skip=("LayerNorm",)):
    """theta~ = theta + sigma eps (Plappert et al. §3) with eps = `perturbation` (params, key)."""
    return apply_perturbation(params, perturbation(params, key, skip), sigma, skip)


def episode_keys(key: chex.PRNGKey, carry_keys: chex.Array, first: chex.Array) -> chex.Array:
    """Each env's perturbation key [n, 2]: a fresh one where an episode starts, else the held one."""
    fresh = jax.random.split(key, first.shape[0])
    return jnp.where(first[:, None], fresh, carry_keys)


class PsneCarry(NamedTuple):
    """Per-env state.

    Attributes:
      key: [n, 2] uint32, the key of this episode's perturbation.
      sigma: [n] the current noise scale (the same in every env).
      eps: [n, P] this episode's eps = `perturbation` (net, key), held so that acting
        draws it once per episode rather than at every step (it depends on the
        parameters' shapes only, so it stays right across updates); the loss reads it
        for the episode each segment starts in (`batch_log_prob`).
    """

    key: jax.Array
    sigma: jax.Array
    eps: jax.Array


class ParameterNoise(OnPolicyStrategy):
    """PSNE for A2C/PPO: every layer perturbed with one adaptive scalar sigma, LayerNorm in between."""

    name = "psne"

    def __init__(self, action_size: int, hidden, activation: str, init_std: float, rule: SigmaRule):
        self.action_size = int(action_size)
        self.net = MeanHead(tuple(hidden), activation, self.action_size, layer_norm=True)
        self.init_std = float(init_std)
        self.rule = rule

    @classmethod
    def from_config(cls, cfg, action_size: int):
        hidden, activation = cfg.policy_hidden, cfg.activation
        return cls(action_size, hidden, activation, cfg.init_std, SigmaRule.from_options(cfg.psne))

    def init(self, key, obs_size):
        return {
            "net": self.net.init(key, jnp.zeros((1, obs_size))),
            "log_std": jnp.full((self.action_size,), math.log(self.init_std), jnp.float32),
        }

    def init_hparams(self) -> SigmaHParams:
        return self.rule.hparams(with_sigma=False)  # sigma is per-env state (the carry)

    def init_carry(self, key, params, hparams, num_envs):
        keys = jax.random.split(key, num_envs)
        return PsneCarry(
            key=keys,
            sigma=jnp.full((num_envs,), self.rule.sigma_init, jnp.float32),
            eps=self._draw(params, keys),
        )

    def _draw(self, params, keys):
        """eps [n, P] of each env's key."""
        return jax.vmap(lambda k: perturbation(params["net"], k))(keys)

    def _mean(self, net_params, obs):
        return self.net.apply(net_params, obs)[1]

    def _perturbed_mean(self, params, keys, sigma, obs):
        """f_theta~(s) per env: keys [n, 2], sigma [n], obs [n, ..., o]."""

        def one(k, s, o):
            return self._mean(perturb(params["net"], k, s), o)

        return jax.vmap(one)(keys, sigma, obs)

    def _held_mean(self, params, eps, sigma, obs):
        """f_theta~(s) per env from held draws: eps [n, P], sigma [n], obs [n, ..., o]."""

        def one(e, s, o):
            return self._mean(apply_perturbation(params["net"], e, s), o)

        return jax.vmap(one)(eps, sigma, obs)

    def act(self, key, params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        k_ep, k_a = jax.random.split(key)
        keys = episode_keys(k_ep, carry.key, first)
        # New draws only at a step where some episode starts (all envs at once, kept where none does).
        eps = jax.lax.cond(
            any_point(jnp.any(first)),
            lambda: jnp.where(first[:, None], self._draw(params, keys), carry.eps),
            lambda: carry.eps,
        )
        mean = self._held_mean(params, eps, carry.sigma, obs)
        log_std = jnp.broadcast_to(params["log_std"], mean.shape)
        action = mean + jnp.exp(log_std) * jax.random.normal(k_a, mean.shape, mean.dtype)
        carry = carry._replace(key=keys, eps=eps)
        return ActOutput(action, gaussian_log_prob(action, mean, log_std), carry, extras=keys)

    def adapt(self, params, hparams, carry, obs):
        # (4.50) on the segment's states, each env under its current perturbation; (4.51).
        chex.assert_rank(obs, 3)
        mean = self._mean(params["net"], obs)  # [T, n, p]
        perturbed = self._held_mean(params, carry.eps, carry.sigma, jnp.swapaxes(obs, 0, 1))
        distance = policy_distance(
            mean.reshape(-1, mean.shape[-1]), jnp.swapaxes(perturbed, 0, 1).reshape(-1, mean.shape[-1])
        )
        sigma = adapt_sigma(carry.sigma, distance, hparams.sigma_delta, hparams.sigma_alpha)
        return carry._replace(sigma=sigma)

    def log_prob(self, params, hparams, segment):
        segment.check()
        chex.assert_rank(segment.extras, 2)  # each step's episode key [T, 2]
        obs = segment.obs
        sigma = jnp.broadcast_to(segment.carry0.sigma, (obs.shape[0],))  # the sigma of collection
        mean = self._perturbed_mean(params, segment.extras, sigma, obs)
        log_std = jnp.broadcast_to(params["log_std"], mean.shape)
        return SegmentLogProb(gaussian_log_prob(segment.action, mean, log_std), gaussian_entropy(log_std))

    def batch_log_prob(self, params, hparams, segment, capacity=None, draw_capacity=None):
        """`log_prob` of a minibatch of m segments [T, m], each episode's perturbation drawn once.

        A step's perturbation is a function of its episode's key, and keys change only
        where an episode starts. A segment's first episode is the one its env was in
        when the segment began, whose eps the carry holds (``carry0.eps``); only the
        F episodes that start inside the segments need a draw. The forward passes run
        in chunks of L = gcd(T, 8) steps: the steps of one chunk share one episode and
        one window [kL, (k+1)L) of their segment, so each chunk takes one perturbed
        network and the minibatch holds C = m T / L + (episode starts off the window
        grid) of them (not one per step: that moved m T P floats per minibatch, most of
        PSNE's iteration time; nor one per episode padded to T steps, mostly padding).

        When F <= ``draw_capacity`` (default m max(1, T // 16): up to T // 16 episode
        starts per segment on average) and C <= ``capacity`` (default m T / L +
        ``draw_capacity``), that is how the minibatch is scored; with more episodes
        (short ones early in training) every step draws its own, as `log_prob` does.
        Either way the values are `log_prob`'s. PPO-PSNE's iteration on HalfCheetah
        (64 envs x 64 steps, 8 minibatches, 10 epochs): 0.87 s with one network per
        step, 0.41 s chunked, against 0.19 s for action noise (one process, interleaved).
        """
        segment.check(batch_rank=1)
        obs, carry0, extras = segment.obs, segment.carry0, segment.extras
        T, m = segment.first.shape
        L = math.gcd(T, 8)
        draw_capacity = m * max(1, T // 16) if draw_capacity is None else int(draw_capacity)
        capacity = m * T // L + draw_capacity if capacity is None else int(capacity)
        # Segment-major steps [m T]; chunks start at episode starts and on the window grid.
        starts = jnp.swapaxes(segment.first, 0, 1)  # [m, T]
        step = jnp.arange(m * T)
        new_chunk = starts.reshape(-1) | (step % L == 0)
        chunk = jnp.cumsum(new_chunk) - 1
        # Whether a step's episode started inside its segment, and which start it was.
        fresh_episode = (jnp.cumsum(starts, axis=1) > 0).reshape(-1)
        start_index = jnp.cumsum(starts.reshape(-1)) - 1
        keys = jnp.swapaxes(extras, 0, 1).reshape(m * T, -1)
        sigma = jnp.repeat(carry0.sigma, T)  # the sigma of each segment's collection
        flat_obs = jnp.swapaxes(obs, 0, 1).reshape(m * T, -1)

        def chunked():
            fresh = self._draw(
                params, keys[jnp.nonzero(starts.reshape(-1), size=draw_capacity, fill_value=0)[0]]
            )
            at = jnp.nonzero(new_chunk, size=capacity, fill_value=0)[0]  # each chunk's first step
            eps = jnp.where(
                fresh_episode[at, None], fresh[jnp.clip(start_index[at], 0)], carry0.eps[at // T]
            )  # [capacity, P]
            pos = step - at[chunk]
            rows = jnp.zeros((capacity, L, flat_obs.shape[-1]), flat_obs.dtype).at[chunk, pos].set(flat_obs)
            return self._held_mean(params, eps, sigma[at], rows)[chunk, pos]

        def per_step():
            return self._perturbed_mean(params, keys, sigma, flat_obs)

        fits = (chunk[-1] < capacity) & (start_index[-1] < draw_capacity)
        mean = jax.lax.cond(all_points(fits), chunked, per_step)  # one branch for a whole sweep
        mean = jnp.swapaxes(mean.reshape(m, T, -1), 0, 1)
        log_std = jnp.broadcast_to(params["log_std"], mean.shape)
        return SegmentLogProb(gaussian_log_prob(segment.action, mean, log_std), gaussian_entropy(log_std))

    def mean_action(self, params, obs):
        return self._mean(params["net"], obs)

    def metrics(self, params, hparams):
        return {"action_std": jnp.mean(jnp.exp(params["log_std"]))}


def _perturb_actor(actor_params, key, sigma):
    """The SAC actor with trunk and mean head perturbed (log-std head untouched)."""
    noisy = perturb({"trunk": actor_params["trunk"], "mu": actor_params["mu"]}, key, sigma)
    return {**actor_params, "trunk": noisy["trunk"], "mu": noisy["mu"]}


class PsneBehaviour(OffPolicyBehaviour):
    """PSNE for SAC: the LayerNorm actor's trunk and mean head perturbed per episode."""

    name = "psne"
    actor_layer_norm = True

    def __init__(self, rule: SigmaRule):
        self.rule = rule

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(SigmaRule.from_options(cfg.psne))

    def init_hparams(self) -> SigmaHParams:
        return self.rule.hparams()

    def init_carry(self, key, actor, actor_params, hparams, num_envs):
        return jax.random.split(key, num_envs)  # [n, 2] episode keys

    def act(self, key, actor, actor_params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        k_ep, k_a = jax.random.split(key)
        keys = episode_keys(k_ep, carry, first)

        def one(k, o):
            return actor.dist(_perturb_actor(actor_params, k, hparams.sigma), o[None])

        dist = jax.tree.map(lambda v: v[:, 0], jax.vmap(one)(keys, obs))
        action, _ = squash(k_a, dist)
        return action, keys

    def adapt(self, key, actor, actor_params, hparams, obs):
        chex.assert_rank(obs, 2)
        mean = actor.mode(actor_params, obs)
        perturbed = actor.mode(_perturb_actor(actor_params, key, hparams.sigma), obs)
        distance = policy_distance(mean, perturbed)
        sigma = adapt_sigma(hparams.sigma, distance, hparams.sigma_delta, hparams.sigma_alpha)
        return hparams.replace(sigma=sigma), {"sigma": hparams.sigma, "policy_distance": distance}
