"""`Policy`: a run's policy as a user acts with it, one observation or a batch at a time.

    policy = load_policy("runs/hopper-...")            # a run directory or a Hub folder
    action, state = policy.predict(obs)               # deterministic, in the env's action space
    action, state = policy.predict(obs, state, episode_start, deterministic=False)

The deterministic action is the evaluation's: a = m(clip(mu(norm(s)), -1, 1)), with ``norm``
the run's observation normalisation, ``mu`` the algorithm's mean (A2C/PPO: the strategy's
mean action; SAC: tanh of the actor's mean) and ``m`` the task's `ActionMap` (the map
training's tasks apply after `VecEnv.step`'s clip). ``deterministic=False`` acts as
collection acted in training: the strategy's ``act`` (A2C/PPO) or the behaviour's (SAC) with
the run's configured hyperparameters, its per-env noise state (coherent's chain, PSNE's and
NoisyNet's per-episode noise, pink noise, gSDE's and Lattice's noise matrices) carried in
`PolicyState` and reset where ``episode_start`` is true, exactly as training's ``first``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, NamedTuple

import gymnasium
import jax
import numpy as np
import yaml

from coherent_jax.agents.registry import make_behaviour
from coherent_jax.config import Config, from_stored, validate
from coherent_jax.envs.action_map import ActionMap
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.policy.net import PolicyError, PolicyNet, read_policy
from coherent_jax.run.checkpoint import load_config

#: the files of a Hub folder (`coherent_jax.policy.hub`) that `load_policy` reads.
POLICY_FILE = "policy.msgpack"
META_FILE = "policy.json"


class PolicyState(NamedTuple):
    """The noise state of ``n`` envs acting stochastically: ``key`` (the next draws' PRNG key)
    and ``carry`` (the strategy's per-env state, leading axis n; ``()`` for strategies with none)."""

    key: jax.Array
    carry: Any


def _config(policy: PolicyNet) -> Config:
    return validate(from_stored(yaml.safe_load(policy.config_yaml)))


class Policy:
    """A trained policy with ``predict``; see the module docstring for the actions it takes.

    Attributes:
      policy: the `coherent_jax.policy.net.PolicyNet` underneath (a pytree, usable in JAX code).
      action_map: the task's `ActionMap` from [-1, 1] to the env's action space.
      origin: where it was read from: ``source``, ``iteration``, ``env_steps``.
      observation_space, action_space: Gymnasium ``Box``es of the env's observations and actions.
    """

    def __init__(
        self, policy: PolicyNet, action_map: ActionMap, origin: dict[str, Any], seed: int = 0
    ) -> None:
        self.policy = policy
        self.action_map = action_map
        self.origin = dict(origin)
        self.config = _config(policy)
        self.behaviour = make_behaviour(self.config, policy.action_size) if policy.is_sac else None
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (policy.obs_size,), np.float32)
        self.action_space = gymnasium.spaces.Box(action_map.low, action_map.high, dtype=np.float32)
        self._key = jax.random.PRNGKey(seed)
        self._mean = jax.jit(lambda p, obs: action_map(p.mean_action(obs)))
        self._sample = jax.jit(self._act)
        self._start = jax.jit(self._init_carry, static_argnums=2)

    # ------------------------------------------------------------ description
    @property
    def obs_size(self) -> int:
        return self.policy.obs_size

    @property
    def action_size(self) -> int:
        return self.policy.action_size

    def __repr__(self) -> str:
        c = self.config
        steps = self.origin.get("env_steps")
        return (
            f"Policy(task={c.env!r}, algo={c.algo!r}, explore={c.explore!r}, "
            f"env_steps={steps if steps is not None else 'unknown'}, "
            f"obs={self.obs_size}, actions={self.action_size} in {self.action_map.kind} "
            f"[{float(self.action_map.low.min()):g}, {float(self.action_map.high.max()):g}], "
            f"source={self.origin.get('source')!r})"
        )

    # ------------------------------------------------------------ acting
    def _hparams(self) -> Any:
        return (self.behaviour if self.policy.is_sac else self.policy.network).init_hparams()

    def _init_carry(self, p: PolicyNet, key: jax.Array, n: int) -> Any:
        if p.is_sac:
            return self.behaviour.init_carry(key, p.network, p.params, self._hparams(), n)
        return p.network.init_carry(key, p.params, self._hparams(), n)

    def _act(self, p: PolicyNet, state: PolicyState, obs: jax.Array, first: jax.Array):
        key, k_act = jax.random.split(state.key)
        norm = p._norm(obs)
        if p.is_sac:
            action, carry = self.behaviour.act(
                k_act, p.network, p.params, self._hparams(), state.carry, norm, first
            )
        else:
            out = p.network.act(k_act, p.params, self._hparams(), state.carry, norm, first)
            action, carry = out.action, out.carry
        return self.action_map(action), PolicyState(key, carry)

    def initial_state(self, n: int = 1, seed: int | None = None, key: jax.Array | None = None) -> PolicyState:
        """The noise state of ``n`` envs at the start of training's collection (``init_carry``),
        from ``key``, else ``seed``, else the policy's own key stream (`load_policy`'s ``seed``)."""
        if key is None:
            if seed is not None:
                key = jax.random.PRNGKey(seed)
            else:
                self._key, key = jax.random.split(self._key)
        key, k_carry = jax.random.split(key)
        return PolicyState(key, self._start(self.policy, k_carry, int(n)))

    def _obs(self, obs: Any) -> tuple[np.ndarray, bool]:
        x = np.asarray(obs, np.float32)
        if x.ndim not in (1, 2) or x.shape[-1] != self.obs_size:
            raise ValueError(
                f"invalid observation of shape {list(x.shape)} "
                f"(allowed: [{self.obs_size}] or [n, {self.obs_size}])"
            )
        return (x[None], True) if x.ndim == 1 else (x, False)

    @staticmethod
    def _starts(episode_start: Any, n: int) -> np.ndarray:
        """``episode_start`` as [n] bools: one bool is every env's (broadcast), else n bools ([n])."""
        starts = np.asarray(episode_start)
        if starts.ndim == 0:
            return np.full((n,), bool(starts))
        starts = starts.astype(bool).reshape(-1)
        if starts.shape != (n,):
            shape = list(np.shape(episode_start))
            raise ValueError(f"invalid episode_start of shape {shape} (allowed: one bool, or [{n}])")
        return starts

    def predict(
        self,
        obs: Any,
        state: PolicyState | None = None,
        episode_start: Any = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, PolicyState | None]:
        """(action, state) for ``obs`` [o] or [n, o]: action [p] or [n, p] in the env's action space.

        ``deterministic=True`` returns the evaluation action and ``state`` unchanged.
        Otherwise ``state`` (None: a fresh `initial_state`, every env starting an episode)
        carries the strategy's noise; ``episode_start`` [n] (or one bool, for every env) marks
        the envs whose episode starts at ``obs`` (Stable-Baselines3's ``episode_start``; None:
        none, unless ``state`` is None). Pass the returned state to the next call.
        """
        x, single = self._obs(obs)
        n = x.shape[0]
        if deterministic:
            action = np.asarray(self._mean(self.policy, x))
            return (action[0] if single else action), state
        if state is None:
            state = self.initial_state(n)
            first = np.ones((n,), bool)
        else:
            first = np.zeros((n,), bool)
        if episode_start is not None:
            first = first | self._starts(episode_start, n)
        action, state = self._sample(self.policy, state, x, first)
        action = np.asarray(action)
        return (action[0] if single else action), state

    def __call__(self, obs: Any) -> np.ndarray:
        """The deterministic action for ``obs`` [o] or [n, o], in the env's action space."""
        return self.predict(obs)[0]


def _action_map_of(cfg: Config) -> tuple[ActionMap, int, int]:
    env = VecEnv(cfg.env, 1, cfg.episode_length, cfg.physics, cfg.physics_threads)  # its sizes and map
    return ActionMap.of_physics(env.env, env.action_size), env.observation_size, env.action_size


def load_policy(path: str | Path, seed: int = 0) -> Policy:
    """The policy of a run directory (a training run's or a sweep point's) or of a Hub folder
    (``python -m coherent_jax.export RUN_DIR format=hub``). A run directory is read as
    ``python -m coherent_jax.evaluate`` reads it (``checkpoint.msgpack`` verified against
    ``config.yaml``, else ``params.msgpack``); a Hub folder from its ``policy.msgpack`` and
    ``policy.json``. ``seed`` starts the key stream of stochastic `Policy.predict`.
    Raises `ConfigError`, `coherent_jax.run.checkpoint.CheckpointError` or `PolicyError` in one line.
    """
    path = Path(path)
    if (path / POLICY_FILE).is_file() and (path / META_FILE).is_file():
        policy = PolicyNet.from_bytes((path / POLICY_FILE).read_bytes())
        try:
            meta = json.loads((path / META_FILE).read_text())
            amap = ActionMap.from_dict(meta["action_map"])
        except (ValueError, KeyError, TypeError) as exc:
            raise PolicyError(f"{path / META_FILE}: unreadable ({exc})") from None
        return Policy(policy, amap, meta.get("origin", {}), seed)
    cfg = load_config(path)
    amap, obs_size, action_size = _action_map_of(cfg)
    policy, origin = read_policy(path, obs_size, action_size)
    return Policy(policy, amap, origin, seed)
