"""A2C and PPO-Clip (thesis Algorithms 1, 2, 4, 5) with a pluggable exploration strategy.

One training iteration is one pure function ``TrainState -> (TrainState, metrics)``:
the rollout of ``num_envs`` envs for ``unroll_length`` steps (`lax.scan`), GAE,
and every epoch and minibatch of the update, so it jits into one XLA program and
``jax.vmap`` of it runs a sweep. Minibatches are sets of whole env segments in
time order, never shuffled single steps: the coherent strategy's log-probability
is a filter over the segment. What a segment's first step conditions on is the
strategy's: the carry stored when it was collected (a constant of the data, like a
recurrent policy's stored hidden state), nothing (coherent's exact mode restarts its
chain there), or the env's steps before the segment, which the trainer keeps for a
strategy with ``history_length > 0`` (`EpisodeHistory`: coherent's episode mode
re-infers the episode prefix under the current parameters).

The value function is trained in one of two ways. By default (``vf_iters=0``) one
joint loss, policy + ``vf_coef`` x value, takes every step on one Adam at ``lr``. With
``vf_iters > 0`` (Spinning Up's PPO and VPG) the policy's steps see the policy loss
alone, and then the value takes ``vf_iters`` full-batch steps on its own Adam at
``vf_lr`` (thesis Algorithm 1, steps 4 and 5, as two separate fits).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import optax

from coherent_jax.agents import losses
from coherent_jax.agents.onpolicy_state import AgentParams, HParams, RewardNorm, SplitOptState, TrainState
from coherent_jax.agents.registry import make_strategy
from coherent_jax.agents.rollout import EpisodeHistory, episode_metrics, evaluation_metrics, unroll
from coherent_jax.config import Config
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.exploration.base import OnPolicyStrategy, Segment
from coherent_jax.networks import RunningStats, ValueNetwork, normalize, scale_rewards, update_stats
from coherent_jax.sweep_axis import all_points


def make_optimizer(cfg: Config) -> optax.GradientTransformation:
    """Gradient clipping (none if ``max_grad_norm=0``) then Adam's scaling; the learning
    rate (sweepable) is applied by hand. A separately trained value function has its own."""
    clip = [optax.clip_by_global_norm(cfg.ppo.max_grad_norm)] if cfg.ppo.max_grad_norm > 0 else []
    return optax.chain(*clip, optax.scale_by_adam(eps=1e-5))


def init_learner(
    strategy: OnPolicyStrategy,
    value_net: ValueNetwork,
    optimizer: optax.GradientTransformation,
    k_policy: jax.Array,
    k_value: jax.Array,
    obs_size: int,
    separate_value: bool = False,
) -> tuple[AgentParams, Any, RunningStats]:
    """The leading fields of `TrainState`: (params, opt_state, obs_stats) at initialisation.

    With `separate_value` the policy and the value function get an optimiser state each
    (`SplitOptState`); else one state covers both.
    """
    params = AgentParams(
        policy=strategy.init(k_policy, obs_size),
        value=value_net.init(k_value, jnp.zeros((1, obs_size))),
    )
    if separate_value:
        opt_state = SplitOptState(policy=optimizer.init(params.policy), value=optimizer.init(params.value))
    else:
        opt_state = optimizer.init(params)
    return params, opt_state, RunningStats.create(obs_size)


def learner_template(cfg: Config, obs_size: int, action_size: int) -> tuple[AgentParams, Any, RunningStats]:
    """Shapes and dtypes of (params, opt_state, obs_stats), the leading fields of `TrainState`.

    No environment, no compile: what a checkpoint's policy is read with.
    """
    strategy = make_strategy(cfg, action_size)
    value_net = ValueNetwork(tuple(cfg.value_hidden), cfg.activation)
    key = jax.random.PRNGKey(0)
    optimizer, separate = make_optimizer(cfg), cfg.ppo.vf_iters > 0
    return jax.eval_shape(
        lambda k: init_learner(strategy, value_net, optimizer, k, k, obs_size, separate), key
    )


def export(params: AgentParams, obs_stats: RunningStats) -> dict[str, Any]:
    """What evaluation needs (``params.msgpack``): policy, value and observation statistics."""
    return {"policy": params.policy, "value": params.value, "obs_stats": obs_stats}


class OnPolicyTrainer:
    """Builds the pure functions of an A2C/PPO run from a `Config`.

    ``init(key) -> TrainState``, ``iteration(state) -> (state, metrics)`` and
    ``evaluate(state, key) -> metrics`` are pure and jit-able; the object only
    holds static configuration.
    """

    def __init__(self, cfg: Config, env: VecEnv | None = None, eval_env: VecEnv | None = None):
        self.cfg = cfg
        self.env = env or VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
        self.eval_env = eval_env or VecEnv(
            cfg.env, cfg.eval_episodes, cfg.episode_length, cfg.physics, cfg.physics_threads
        )
        self.strategy: OnPolicyStrategy = make_strategy(cfg, self.env.action_size)
        self.value_net = ValueNetwork(tuple(cfg.value_hidden), cfg.activation)
        self.loss = functools.partial(
            losses.onpolicy_loss,
            strategy=self.strategy,
            value_net=self.value_net,
            clipped=cfg.algo == "ppo",
            normalize_advantages=cfg.ppo.normalize_advantages,
            value_in_loss=cfg.ppo.vf_iters == 0,
        )
        self.optimizer = make_optimizer(cfg)
        self.separate_value = cfg.ppo.vf_iters > 0
        if cfg.algo == "ppo":
            self.num_epochs, self.num_minibatches = cfg.ppo.num_epochs, cfg.ppo.num_minibatches
        else:  # A2C: one gradient step on the whole batch (Algorithm 1)
            self.num_epochs, self.num_minibatches = 1, 1

    # ------------------------------------------------------------------ init
    def init_hparams(self) -> HParams:
        c = self.cfg
        f = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        return HParams(
            lr=f(c.lr),
            gamma=f(c.gamma),
            gae_lambda=f(c.ppo.gae_lambda),
            clip_eps=f(c.ppo.clip_eps),
            target_kl=f(c.ppo.target_kl),
            vf_coef=f(c.ppo.vf_coef),
            ent_coef=f(c.ppo.ent_coef),
            explore=self.strategy.init_hparams(),
            vf_lr=f(c.ppo.vf_lr) if self.separate_value else None,
        )

    def init(self, key: jax.Array, hparams: HParams | None = None) -> TrainState:
        hparams = self.init_hparams() if hparams is None else hparams
        k_pol, k_val, k_env, k_carry, key = jax.random.split(key, 5)
        params, opt_state, obs_stats = init_learner(
            self.strategy,
            self.value_net,
            self.optimizer,
            k_pol,
            k_val,
            self.env.observation_size,
            self.separate_value,
        )
        return TrainState(
            params=params,
            opt_state=opt_state,
            obs_stats=obs_stats,
            env_state=self.env.reset(k_env),
            carry=self.strategy.init_carry(k_carry, params.policy, hparams.explore, self.env.num_envs),
            reward_norm=RewardNorm.create(self.env.num_envs),
            hparams=hparams,
            key=key,
            iteration=jnp.zeros((), jnp.int32),
            env_steps=jnp.zeros((), jnp.int32),
            history=self._empty_history(),
        )

    def _empty_history(self) -> EpisodeHistory | tuple:
        length = self.strategy.history_length
        if not length:
            return ()
        env = self.env
        return EpisodeHistory.empty(length, env.num_envs, env.observation_size, env.action_size)

    # ------------------------------------------------------------- iteration
    def _norm(self, stats: RunningStats, obs: jax.Array) -> jax.Array:
        return normalize(stats, obs, self.cfg.normalize_obs)

    def iteration(self, state: TrainState) -> tuple[TrainState, dict[str, jax.Array]]:
        """Collect, estimate advantages, update (one jit-able step)."""
        cfg, hp, params, stats = self.cfg, state.hparams, state.params, state.obs_stats
        key, k_roll, k_perm = jax.random.split(state.key, 3)
        strategy = self.strategy

        def act(k, carry, obs, first):
            return strategy.act(k, params.policy, hp.explore, carry, self._norm(stats, obs), first)

        carry0 = state.carry
        env_state, carry, data = unroll(self.env, act, state.env_state, carry0, k_roll, cfg.unroll_length)
        obs = self._norm(stats, data.obs)
        context = self._context(state.history, stats)
        segment = Segment(obs=obs, action=data.action, first=data.first, carry0=carry0, extras=data.extras)
        # Strategies may score the whole segment at once (coherent: joint Gaussian), and
        # adapt their noise on its states (PSNE).
        behaviour_log_prob, carry = self._score(params, hp, segment, carry, data.log_prob, context)
        carry = strategy.adapt(params.policy, hp.explore, carry, obs)
        data = data._replace(log_prob=behaviour_log_prob)
        values = self.value_net.apply(params.value, obs)
        next_values = self.value_net.apply(params.value, self._norm(stats, data.final_obs))
        reward_norm, rewards = self._scaled_rewards(state.reward_norm, data, hp.gamma)
        advantages, targets = losses.gae(
            rewards, values, next_values, data.terminated, data.done, hp.gamma, hp.gae_lambda
        )
        batch = losses.SegmentBatch(
            segment=segment,
            behaviour_log_prob=behaviour_log_prob,
            advantages=advantages,
            targets=targets,
            context=context,
        )
        new_params, opt_state, metrics = self._update(params, state.opt_state, hp, batch, k_perm)
        n = self.env.num_envs

        metrics.update(episode_metrics(data, self.env.goal))
        var_t = targets.var()
        metrics["train/explained_variance"] = 1.0 - (targets - values).var() / (var_t + 1e-8)
        if cfg.ppo.normalize_rewards:
            metrics["train/return_std"] = jnp.sqrt(reward_norm.stats.var[0])
        metrics.update({f"train/{k}": v for k, v in strategy.metrics(new_params.policy, hp.explore).items()})

        new_stats = update_stats(stats, data.obs) if cfg.normalize_obs else stats
        new_state = state.replace(
            params=new_params,
            opt_state=opt_state,
            obs_stats=new_stats,
            env_state=env_state,
            carry=carry,
            reward_norm=reward_norm,
            key=key,
            iteration=state.iteration + 1,
            env_steps=state.env_steps + n * cfg.unroll_length,
            history=state.history.extend(data) if state.history else (),
        )
        return new_state, metrics

    def _update(self, params: AgentParams, opt_state, hp: HParams, batch, key: jax.Array):
        """The update of one iteration: the joint loss's steps, or (``vf_iters > 0``) the
        policy's steps on the policy loss alone, then the value's on its own optimiser.

        Returns:
          (params, opt_state, metrics).
        """
        if not self.separate_value:
            return self._policy_steps(params, opt_state, lambda p, sub: self.loss(p, hp, sub), hp, batch, key)
        policy, policy_opt, metrics = self._policy_steps(
            params.policy,
            opt_state.policy,
            lambda pol, sub: self.loss(params.replace(policy=pol), hp, sub),
            hp,
            batch,
            key,
        )
        value, value_opt, value_metrics = self._value_steps(
            params.value, opt_state.value, hp, batch.segment.obs, batch.targets
        )
        metrics.update(value_metrics)
        return AgentParams(policy=policy, value=value), SplitOptState(policy_opt, value_opt), metrics

    def _policy_steps(self, trainable, opt_state, loss_fn, hp: HParams, batch, key: jax.Array):
        """``num_epochs`` x ``num_minibatches`` Adam steps at ``lr`` on `loss_fn`, stopping early.

        `trainable` is every parameter (the joint loss) or the policy's alone;
        ``loss_fn(trainable, minibatch) -> (loss, metrics)``. Each step first evaluates the
        loss and its approximate KL at the current parameters, and once the KL exceeds
        1.5 x ``target_kl`` no further step is applied (Algorithms 2 and 5).

        Returns:
          (trainable, opt_state, metrics averaged over the applied steps).
        """
        n, mb = self.env.num_envs, self.num_minibatches
        grad_fn = jax.value_and_grad(loss_fn, has_aux=True)

        def sgd_step(c, env_idx):
            params, opt_state, stopped = c
            sub = batch.envs(env_idx)
            (_, aux), grads = self._grad_unless_stopped(grad_fn, params, sub, stopped)
            # Algorithm 2/5: stop the epochs once the approximate KL is too large.
            too_far = jnp.logical_and(hp.target_kl > 0, aux["approx_kl"] > 1.5 * hp.target_kl)
            stop = jnp.logical_or(stopped, too_far)

            def apply(args):
                params, opt_state = args
                updates, opt_state = self.optimizer.update(grads, opt_state, params)
                params = jax.tree.map(lambda p, u: p - hp.lr * u, params, updates)
                return params, opt_state

            params, opt_state = jax.lax.cond(stop, lambda a: a, apply, (params, opt_state))
            aux["grad_norm"] = optax.global_norm(grads)
            aux["applied"] = (~stop).astype(jnp.float32)
            return (params, opt_state, stop), aux

        def epoch(c, k):
            perm = jax.random.permutation(k, n).reshape(mb, n // mb)
            return jax.lax.scan(sgd_step, c, perm)

        (trainable, opt_state, _), aux = jax.lax.scan(
            epoch, (trainable, opt_state, jnp.zeros((), bool)), jax.random.split(key, self.num_epochs)
        )
        applied = aux.pop("applied")
        weight = applied / jnp.maximum(applied.sum(), 1.0)
        metrics = {f"train/{k}": jnp.sum(v * weight) for k, v in aux.items()}
        metrics["train/updates_applied"] = applied.sum()
        metrics["train/kl_first_minibatch"] = aux["approx_kl"][0, 0]
        return trainable, opt_state, metrics

    def _grad_unless_stopped(self, grad_fn, params, sub, stopped: jax.Array):
        """``grad_fn(params, sub)``, or zeros once the epochs have stopped early at every
        point of a sweep (Spinning Up's PPO breaks out of its policy steps there; a stopped
        step applies nothing and weighs nothing in the metrics). Only with a KL target set
        in the config (static): without one no step ever stops."""
        if not self.cfg.ppo.target_kl > 0:
            return grad_fn(params, sub)
        zeros = lambda _: jax.tree.map(  # noqa: E731
            lambda v: jnp.zeros(v.shape, v.dtype), jax.eval_shape(grad_fn, params, sub)
        )
        return jax.lax.cond(all_points(stopped), zeros, lambda _: grad_fn(params, sub), None)

    def _value_steps(self, value_params, opt_state, hp: HParams, obs: jax.Array, targets: jax.Array):
        """``vf_iters`` Adam steps at ``vf_lr`` on the value loss of the whole batch (Algorithm 1, step 5).

        Returns:
          (value_params, opt_state, metrics: the value loss and gradient norm, averaged over the steps).
        """

        def loss(v):
            return losses.value_loss(self.value_net.apply(v, obs), targets)

        def step(c, _):
            v, o = c
            value, grads = jax.value_and_grad(loss)(v)
            updates, o = self.optimizer.update(grads, o, v)
            v = jax.tree.map(lambda p, u: p - hp.vf_lr * u, v, updates)
            return (v, o), (value, optax.global_norm(grads))

        (value_params, opt_state), (value, grad_norm) = jax.lax.scan(
            step, (value_params, opt_state), None, length=self.cfg.ppo.vf_iters
        )
        metrics = {"train/value_loss": value.mean(), "train/value_grad_norm": grad_norm.mean()}
        return value_params, opt_state, metrics

    def _context(self, history: EpisodeHistory | tuple, stats: RunningStats) -> EpisodeHistory | tuple:
        """The steps before the segment as the loss reads them: observations normalised with
        this iteration's statistics, like the segment's."""
        if not history:
            return ()
        return history._replace(obs=self._norm(stats, history.obs))

    def _score(self, params, hp, segment: Segment, carry, log_prob, context) -> tuple[jax.Array, Any]:
        """`strategy.score_segment` of the segment [T, n] (``log_prob`` what `act` returned),
        on windows context + segment when the strategy reads a history (`Segment.after`;
        the last T log-probabilities kept)."""
        if not context:
            return self.strategy.score_segment(params.policy, hp.explore, segment, carry, log_prob)
        unscored = jnp.full(context.first.shape, jnp.nan)
        log_prob, carry = self.strategy.score_segment(
            params.policy,
            hp.explore,
            segment.after(context),
            carry,
            jnp.concatenate([unscored, log_prob.astype(unscored.dtype)]),
        )
        return log_prob[-segment.obs.shape[0] :], carry

    def _scaled_rewards(self, norm: RewardNorm, data, gamma: jax.Array) -> tuple[RewardNorm, jax.Array]:
        """The rewards GAE and the value targets see: as collected, or with
        ``normalize_rewards`` divided by the running std of the discounted return, the
        statistics first merged with this segment's returns (Gymnasium's NormalizeReward
        order). Episode returns and evaluations always report the task's own rewards."""
        if not self.cfg.ppo.normalize_rewards:
            return norm, data.reward
        running, returns = losses.discounted_returns(norm.discounted_return, data.reward, data.done, gamma)
        stats = update_stats(norm.stats, returns[..., None])
        return RewardNorm(stats=stats, discounted_return=running), scale_rewards(stats, data.reward)

    def export_params(self, state: TrainState) -> dict[str, Any]:
        """What evaluation needs: policy, value and observation statistics (`export`)."""
        return export(state.params, state.obs_stats)

    # ------------------------------------------------------------ evaluation
    def evaluate(self, state: TrainState, key: jax.Array) -> dict[str, jax.Array]:
        """Deterministic (mean-action) episodes, one per eval env."""
        params, stats = state.params, state.obs_stats

        def policy(obs):
            return self.strategy.mean_action(params.policy, self._norm(stats, obs))

        return evaluation_metrics(self.eval_env, policy, key)
