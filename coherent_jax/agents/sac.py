"""Soft Actor-Critic (thesis §2.4.3, Algorithm 3) and Coherent-SAC (§4.3, §4.4.3).

One training iteration is one pure function ``TrainState -> (TrainState, metrics)``:
collect ``unroll_length`` steps of ``num_envs`` envs (`lax.scan`), insert them into
the replay ring buffer held in the state, then ``updates_per_iteration`` gradient
updates (another `lax.scan`), then let the exploration strategy adapt its noise
scale on a replay batch. Collection uses uniform random actions until
``warmup_steps`` env steps are done, and updates start once ``update_after`` are
(by default the same number; Spinning Up starts updates earlier, during the random
actions: start_steps 10,000, update_after 1,000).

Each gradient update (Algorithm 3, steps 9-14):

    y = r + gamma (1 - d) (min_i Q_targ,i(s', a') - alpha log pi(a'|s')),  a' ~ pi(.|s')   (2.47)
    L(phi_i) = E[(Q_phi_i(s, a) - y)^2]                                             (2.46)
    J(theta) = E[min_i Q_phi_i(s, a~) - alpha log pi(a~|s)],  a~ = tanh(mu + sigma xi)  (2.50, 2.51)
    phi_targ,i <- rho phi_targ,i + (1 - rho) phi_i,  rho = 1 - tau                  (step 14)

and, with ``auto_temperature``, alpha follows the entropy target (Haarnoja et al.
2018b): L(log alpha) = -E[log alpha (log pi(a~|s) + target_entropy)].

The losses are `coherent_jax.agents.sac_losses`. The exploration strategy only shapes
behaviour (`coherent_jax.exploration.base.OffPolicyBehaviour`): for
``explore=action`` that is SAC's own sample; for ``explore=coherent`` the actor's
mean head follows the beta-chain around its learned weights with scale sigma, and
sigma adapts by (4.50)-(4.51). Training of Q and actor is plain SAC either way.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from coherent_jax.agents import sac_losses
from coherent_jax.agents.registry import make_behaviour
from coherent_jax.agents.replay import Experience, ReplayBuffer, replay_add, replay_init, replay_sample
from coherent_jax.agents.rollout import episode_metrics, evaluation_metrics, unroll
from coherent_jax.config import Config
from coherent_jax.envs.vec_env import EnvState, VecEnv
from coherent_jax.exploration.base import ActOutput, OffPolicyBehaviour
from coherent_jax.networks import QNetwork, RunningStats, SquashedGaussianActor, normalize, update_stats


@struct.dataclass
class SACHParams:
    """Scalars that may vary across the points of a vmapped sweep (all arrays)."""

    lr: jax.Array
    gamma: jax.Array
    tau: jax.Array
    temperature: jax.Array
    target_entropy: jax.Array
    explore: Any  # the strategy's own hyperparameters (a flax.struct.dataclass)


@struct.dataclass
class SACParams:
    """Trainable parameters and the target critics.

    Attributes:
      actor: `SquashedGaussianActor` parameters.
      critic: the twin Q-networks, stacked on a leading axis of size 2.
      target_critic: the Polyak-averaged copies phi_targ (not trained by gradient).
      log_alpha: log of the temperature (trained only with ``auto_temperature``).
    """

    actor: Any
    critic: Any
    target_critic: Any
    log_alpha: jax.Array


@struct.dataclass
class SACOptState:
    actor: Any
    critic: Any
    alpha: Any


@struct.dataclass
class SACTrainState:
    """Everything an iteration reads and writes; the replay buffer included."""

    params: SACParams
    opt_state: SACOptState
    obs_stats: RunningStats
    env_state: EnvState
    carry: Any
    buffer: ReplayBuffer
    hparams: SACHParams
    key: jax.Array
    iteration: jax.Array
    env_steps: jax.Array


def polyak_update(target: Any, online: Any, tau: jax.Array) -> Any:
    """phi_targ <- (1 - tau) phi_targ + tau phi, leaf by leaf (Algorithm 3, step 14, rho = 1 - tau)."""
    return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def make_actor(cfg: Config, action_size: int, behaviour: OffPolicyBehaviour) -> SquashedGaussianActor:
    """SAC's actor; LayerNorm between its layers if the behaviour asks for it (PSNE), and
    the mean head's init gain it asks for (Lattice)."""
    return SquashedGaussianActor(
        action_size,
        cfg.policy_hidden,
        cfg.activation,
        layer_norm=behaviour.actor_layer_norm,
        head_gain=behaviour.actor_head_gain,
    )


def init_learner(
    actor: SquashedGaussianActor,
    critic: QNetwork,
    adam: optax.GradientTransformation,
    k_actor: jax.Array,
    k_critic: jax.Array,
    obs_size: int,
    action_size: int,
    temperature: jax.Array,
) -> tuple[SACParams, SACOptState, RunningStats]:
    """The leading fields of `SACTrainState`: (params, opt_state, obs_stats) at initialisation."""
    actor_params = actor.init(k_actor, obs_size)
    dummy_obs, dummy_act = jnp.zeros((1, obs_size)), jnp.zeros((1, action_size))
    critic_params = jax.vmap(lambda k: critic.init(k, dummy_obs, dummy_act))(jax.random.split(k_critic))
    params = SACParams(
        actor=actor_params, critic=critic_params, target_critic=critic_params, log_alpha=jnp.log(temperature)
    )
    opt_state = SACOptState(
        actor=adam.init(actor_params), critic=adam.init(critic_params), alpha=adam.init(params.log_alpha)
    )
    return params, opt_state, RunningStats.create(obs_size)


def learner_template(
    cfg: Config, obs_size: int, action_size: int
) -> tuple[SACParams, SACOptState, RunningStats]:
    """Shapes and dtypes of (params, opt_state, obs_stats), the leading fields of `SACTrainState`.

    No environment, no replay buffer, no compile: what a checkpoint's actor is read with.
    """
    actor = make_actor(cfg, action_size, make_behaviour(cfg, action_size))
    critic = QNetwork(tuple(cfg.value_hidden), cfg.activation)
    return jax.eval_shape(
        lambda k: init_learner(
            actor, critic, optax.scale_by_adam(), k, k, obs_size, action_size, jnp.ones((), jnp.float32)
        ),
        jax.random.PRNGKey(0),
    )


def export(params: SACParams, obs_stats: RunningStats) -> dict[str, Any]:
    """What evaluation needs (``params.msgpack``): actor, critics and observation statistics."""
    return {"actor": params.actor, "critic": params.critic, "obs_stats": obs_stats}


class SACTrainer:
    """Builds the pure functions of a SAC / Coherent-SAC run from a `Config`.

    ``init(key) -> SACTrainState``, ``iteration(state) -> (state, metrics)`` and
    ``evaluate(state, key) -> metrics`` are pure and jit-able, as for
    `OnPolicyTrainer`.
    """

    def __init__(self, cfg: Config, env: VecEnv | None = None, eval_env: VecEnv | None = None):
        if cfg.algo != "sac":
            raise ValueError(f"SACTrainer needs algo='sac', got {cfg.algo!r}")
        self.cfg = cfg
        self.env = env or VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
        self.eval_env = eval_env or VecEnv(
            cfg.env, cfg.eval_episodes, cfg.episode_length, cfg.physics, cfg.physics_threads
        )
        self.action_size = self.env.action_size
        self.behaviour: OffPolicyBehaviour = make_behaviour(cfg, self.action_size)
        self.actor = make_actor(cfg, self.action_size, self.behaviour)
        self.critic = QNetwork(tuple(cfg.value_hidden), cfg.activation)
        nets = {"actor": self.actor, "critic": self.critic}
        self.critic_target = functools.partial(sac_losses.critic_target, **nets)
        self.critic_loss = functools.partial(sac_losses.critic_loss, critic=self.critic)
        self.actor_loss = functools.partial(sac_losses.actor_loss, **nets)
        self.adam = optax.scale_by_adam()
        self.num_updates = cfg.updates_per_iteration
        self.batch_size = cfg.sac.batch_size

    # ------------------------------------------------------------------ init
    def init_hparams(self) -> SACHParams:
        c = self.cfg
        f = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        target_entropy = -float(self.action_size) if c.sac.target_entropy is None else c.sac.target_entropy
        return SACHParams(
            lr=f(c.lr),
            gamma=f(c.gamma),
            tau=f(c.sac.tau),
            temperature=f(c.sac.temperature),
            target_entropy=f(target_entropy),
            explore=self.behaviour.init_hparams(),
        )

    def init(self, key: jax.Array, hparams: SACHParams | None = None) -> SACTrainState:
        hp = self.init_hparams() if hparams is None else hparams
        k_actor, k_critic, k_env, k_carry, key = jax.random.split(key, 5)
        obs_size, p = self.env.observation_size, self.action_size
        params, opt_state, obs_stats = init_learner(
            self.actor, self.critic, self.adam, k_actor, k_critic, obs_size, p, hp.temperature
        )
        return SACTrainState(
            params=params,
            opt_state=opt_state,
            obs_stats=obs_stats,
            env_state=self.env.reset(k_env),
            carry=self.behaviour.init_carry(k_carry, self.actor, params.actor, hp.explore, self.env.num_envs),
            buffer=replay_init(self.cfg.sac.buffer_size, obs_size, p),
            hparams=hp,
            key=key,
            iteration=jnp.zeros((), jnp.int32),
            env_steps=jnp.zeros((), jnp.int32),
        )

    # --------------------------------------------------------------- helpers
    def _norm(self, stats: RunningStats, obs: jax.Array) -> jax.Array:
        return normalize(stats, obs, self.cfg.normalize_obs)

    def _apply_adam(self, grads, opt_state, params, lr):
        updates, opt_state = self.adam.update(grads, opt_state, params)
        return jax.tree.map(lambda p, u: p - lr * u, params, updates), opt_state

    # ---------------------------------------------------------------- update
    def update(
        self, params: SACParams, opt: SACOptState, hp: SACHParams, batch: Experience, key: jax.Array
    ) -> tuple[SACParams, SACOptState, dict[str, jax.Array]]:
        """One gradient update of critics, actor and (optionally) temperature, then Polyak.

        ``batch`` holds normalised observations. Pure; Algorithm 3, steps 10-14.
        """
        k_next, k_pi = jax.random.split(key)
        alpha = jnp.exp(params.log_alpha)
        y = self.critic_target(params.actor, params.target_critic, batch, k_next, hp.gamma, alpha)
        (c_loss, q), c_grads = jax.value_and_grad(self.critic_loss, has_aux=True)(params.critic, batch, y)
        critic, opt_critic = self._apply_adam(c_grads, opt.critic, params.critic, hp.lr)

        # The actor's objective uses the updated critics (Algorithm 3, steps 12-13).
        (a_loss, log_prob), a_grads = jax.value_and_grad(self.actor_loss, has_aux=True)(
            params.actor, critic, batch, k_pi, alpha
        )
        actor, opt_actor = self._apply_adam(a_grads, opt.actor, params.actor, hp.lr)

        log_alpha, opt_alpha = params.log_alpha, opt.alpha
        if self.cfg.sac.auto_temperature:
            alpha_grad = jax.grad(sac_losses.temperature_loss)(params.log_alpha, log_prob, hp.target_entropy)
            log_alpha, opt_alpha = self._apply_adam(alpha_grad, opt.alpha, params.log_alpha, hp.lr)

        new_params = SACParams(
            actor=actor,
            critic=critic,
            target_critic=polyak_update(params.target_critic, critic, hp.tau),
            log_alpha=log_alpha,
        )
        metrics = {
            "critic_loss": c_loss,
            "actor_loss": a_loss,
            "q_mean": jnp.mean(q),
            "target_mean": jnp.mean(y),
            "entropy": -jnp.mean(log_prob),
            "temperature": alpha,
            "actor_grad_norm": optax.global_norm(a_grads),
            "critic_grad_norm": optax.global_norm(c_grads),
        }
        return new_params, SACOptState(actor=opt_actor, critic=opt_critic, alpha=opt_alpha), metrics

    # ------------------------------------------------------------- iteration
    def iteration(self, state: SACTrainState) -> tuple[SACTrainState, dict[str, jax.Array]]:
        """Collect K env steps into the buffer, then U updates and one adaptation (one jit-able step)."""
        cfg, hp, stats = self.cfg, state.hparams, state.obs_stats
        key, k_roll, k_updates, k_adapt, k_batch = jax.random.split(state.key, 5)
        actor_params = state.params.actor
        warm = state.env_steps < cfg.sac.warmup_steps  # Algorithm 3 preceded by uniform random actions
        n, p = self.env.num_envs, self.action_size

        def act(k, carry, obs, first):
            k_act, k_uniform = jax.random.split(k)
            action, carry = self.behaviour.act(
                k_act, self.actor, actor_params, hp.explore, carry, self._norm(stats, obs), first
            )
            uniform = jax.random.uniform(k_uniform, (n, p), minval=-1.0, maxval=1.0)
            action = jnp.where(warm, uniform, action)
            return ActOutput(action, jnp.zeros((n,), action.dtype), carry)

        env_state, carry, data = unroll(
            self.env, act, state.env_state, state.carry, k_roll, cfg.unroll_length
        )
        flat = lambda x: x.reshape((-1,) + x.shape[2:])  # noqa: E731  [T, n, ...] -> [T n, ...]
        buffer = replay_add(
            state.buffer,
            Experience(
                obs=flat(data.obs),
                action=flat(data.action),
                reward=flat(data.reward),
                next_obs=flat(data.final_obs),
                terminated=flat(data.terminated).astype(jnp.float32),
            ),
        )
        env_steps = state.env_steps + n * cfg.unroll_length
        # Statistics first, so that every update of this iteration sees the same normalisation.
        new_stats = update_stats(stats, data.obs) if cfg.normalize_obs else stats

        def sample(k):
            b = replay_sample(buffer, k, self.batch_size)
            return b._replace(obs=self._norm(new_stats, b.obs), next_obs=self._norm(new_stats, b.next_obs))

        def one_update(c, k):
            params, opt = c
            k_sample, k_update = jax.random.split(k)
            params, opt, m = self.update(params, opt, hp, sample(k_sample), k_update)
            return (params, opt), m

        def train(args):
            params, opt, explore = args
            (params, opt), m = jax.lax.scan(
                one_update, (params, opt), jax.random.split(k_updates, self.num_updates)
            )
            m = jax.tree.map(jnp.mean, m)
            explore, adapt_m = self.behaviour.adapt(
                k_adapt, self.actor, params.actor, explore, sample(k_batch).obs
            )
            return params, opt, explore, m, adapt_m

        ready = env_steps >= (cfg.sac.warmup_steps if cfg.sac.update_after is None else cfg.sac.update_after)
        _, _, _, m_shape, a_shape = jax.eval_shape(train, (state.params, state.opt_state, hp.explore))
        nan_like = lambda tree: jax.tree.map(lambda s: jnp.full(s.shape, jnp.nan, s.dtype), tree)  # noqa: E731

        def skip(args):
            params, opt, explore = args
            return params, opt, explore, nan_like(m_shape), nan_like(a_shape)

        params, opt_state, explore, m, adapt_m = jax.lax.cond(
            ready, train, skip, (state.params, state.opt_state, hp.explore)
        )

        metrics = {f"train/{k}": v for k, v in m.items()}
        metrics.update({f"train/{k}": v for k, v in adapt_m.items()})
        metrics["train/updates_applied"] = jnp.where(ready, float(self.num_updates), 0.0)
        metrics["train/warmup"] = warm.astype(jnp.float32)
        metrics["train/buffer_size"] = buffer.size.astype(jnp.float32)
        metrics.update(episode_metrics(data, self.env.goal))

        new_state = state.replace(
            params=params,
            opt_state=opt_state,
            obs_stats=new_stats,
            env_state=env_state,
            carry=carry,
            buffer=buffer,
            hparams=hp.replace(explore=explore),
            key=key,
            iteration=state.iteration + 1,
            env_steps=env_steps,
        )
        return new_state, metrics

    def export_params(self, state: SACTrainState) -> dict[str, Any]:
        """What evaluation needs: actor, critics and observation statistics (`export`)."""
        return export(state.params, state.obs_stats)

    # ------------------------------------------------------------ evaluation
    def evaluate(self, state: SACTrainState, key: jax.Array) -> dict[str, jax.Array]:
        """Deterministic episodes with a = tanh(mean(s)), one per eval env."""
        params, stats = state.params, state.obs_stats

        def policy(obs):
            return self.actor.mode(params.actor, self._norm(stats, obs))

        return evaluation_metrics(self.eval_env, policy, key)
