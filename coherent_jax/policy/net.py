"""`PolicyNet`: a trained policy's network alone, parameters + observation statistics -> action.

The piece under `coherent_jax.policy.trained.Policy` (its ``policy`` attribute) that
evaluation, a video or JAX code needs, and nothing of training: no environments, no
optimiser, no replay buffer, no exploration state.

    net, origin = read_policy(run_dir, obs_size, action_size)   # from checkpoint.msgpack or params.msgpack
    action = net.mean_action(obs)                                # deterministic: the evaluation action
    action = net.sample(key, obs)                                # stochastic (see `PolicyNet.sample`)
    blob = net.to_bytes(); net = PolicyNet.from_bytes(blob)

The network is the algorithm's own: for A2C/PPO the exploration strategy's
(`OnPolicyStrategy.mean_action`), for SAC the squashed Gaussian actor
(tanh of its mean). Observations are normalised with the run's statistics when the
run normalised them. A `PolicyNet` is a pytree (parameters and statistics are its
leaves; the network and settings are static), so
``jax.jit(lambda p, o: p.mean_action(o))`` takes it as an argument.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import msgpack
import numpy as np
import yaml
from flax import serialization, struct
from omegaconf import OmegaConf

from coherent_jax.agents import onpolicy, sac
from coherent_jax.agents.registry import make_behaviour, make_strategy
from coherent_jax.agents.sac import make_actor
from coherent_jax.config import Config, ConfigError, from_stored, to_dict, validate
from coherent_jax.networks import RunningStats, SquashedGaussianActor, normalize, squash
from coherent_jax.run.checkpoint import CHECKPOINT, PARAMS, decode_checkpoint, load_config

FORMAT = "coherent_jax-policy-1"


class PolicyError(ValueError):
    """A policy that cannot be read (missing, corrupted, or shaped for another network)."""


def _agent_module(cfg: Config):
    """The trainer module of ``cfg.algo``: its `learner_template` and `export` say where the policy is."""
    if cfg.algo == "sac":
        return sac
    return onpolicy


def _network(cfg: Config, action_size: int):
    """The object that maps (parameters, normalised obs) to actions: strategy or SAC actor."""
    if cfg.algo == "sac":
        return make_actor(cfg, action_size, make_behaviour(cfg, action_size))
    return make_strategy(cfg, action_size)


@struct.dataclass
class PolicyNet:
    """Parameters and observation statistics of a trained policy, and the network they belong to.

    Attributes:
      params: the policy's parameters (A2C/PPO: the strategy's; SAC: the actor's).
      obs_stats: the run's observation statistics.
      network: the strategy (A2C/PPO) or `SquashedGaussianActor` (SAC) that ``params``
        belong to (static).
      normalize_obs: whether the run normalised observations (static).
      config_yaml: the run's resolved config, as ``config.yaml`` holds it (static).
      obs_size, action_size: sizes (static).
    """

    params: Any
    obs_stats: RunningStats
    network: Any = struct.field(pytree_node=False)
    normalize_obs: bool = struct.field(pytree_node=False)
    config_yaml: str = struct.field(pytree_node=False)
    obs_size: int = struct.field(pytree_node=False)
    action_size: int = struct.field(pytree_node=False)

    @classmethod
    def create(cls, cfg: Config, params: Any, obs_stats: RunningStats, obs_size: int, action_size: int):
        """The policy of a run with config ``cfg``."""
        return cls(
            params=params,
            obs_stats=obs_stats,
            network=_network(cfg, action_size),
            normalize_obs=cfg.normalize_obs,
            config_yaml=OmegaConf.to_yaml(to_dict(cfg)),
            obs_size=int(obs_size),
            action_size=int(action_size),
        )

    @property
    def is_sac(self) -> bool:
        return isinstance(self.network, SquashedGaussianActor)

    def _norm(self, obs: jax.Array) -> jax.Array:
        return normalize(self.obs_stats, obs, self.normalize_obs)

    def mean_action(self, obs: jax.Array) -> jax.Array:
        """The deterministic action, obs [..., o] -> [..., p], as training's evaluation takes it."""
        if self.is_sac:
            return self.network.mode(self.params, self._norm(obs))
        return self.network.mean_action(self.params, self._norm(obs))

    def sample(self, key: jax.Array, obs: jax.Array) -> jax.Array:
        """A stochastic action for a batch of states obs [n, o] -> [n, p].

        SAC: a = tanh(mean + std xi) (eq. 2.50). A2C/PPO: the strategy's action at an
        episode start (a fresh draw of its exploration noise for every state, e.g.
        w_0 ~ N(mu, diag(w_std^2)) for coherent), with the run's configured hyperparameters
        (PSNE: its initial sigma; the adapted one lives in training's carry). A rollout
        that keeps the noise along an episode needs the strategy's carry and belongs to
        training.
        """
        obs = self._norm(obs)
        if self.is_sac:
            return squash(key, self.network.dist(self.params, obs))[0]
        strategy = self.network
        k_carry, k_act = jax.random.split(key)
        hparams = strategy.init_hparams()
        carry = strategy.init_carry(k_carry, self.params, hparams, obs.shape[0])
        first = jnp.ones((obs.shape[0],), bool)
        return strategy.act(k_act, self.params, hparams, carry, obs, first).action

    # ------------------------------------------------------------ serialisation
    def to_bytes(self) -> bytes:
        """The policy as one msgpack record: config, sizes, parameters and statistics."""
        state = serialization.to_state_dict(
            jax.device_get({"params": self.params, "obs_stats": self.obs_stats})
        )
        return msgpack.packb(
            {
                "format": FORMAT,
                "config": self.config_yaml,
                "obs_size": self.obs_size,
                "action_size": self.action_size,
                "state": serialization.msgpack_serialize(state),
            },
            use_bin_type=True,
        )

    @classmethod
    def from_bytes(cls, blob: bytes) -> PolicyNet:
        """The policy `to_bytes` wrote; raises `PolicyError` in one line."""
        try:
            record = msgpack.unpackb(blob, raw=False)
            fmt = record["format"]
        except Exception:  # noqa: BLE001 - any decoding failure means the same thing
            raise PolicyError(f"not a policy record ({len(blob)} bytes)") from None
        if fmt != FORMAT:
            raise PolicyError(f"policy format {fmt!r} (allowed: {FORMAT})")
        cfg = from_stored(yaml.safe_load(record["config"]))  # a flat config of before too
        try:
            cfg = validate(cfg)
        except ConfigError as exc:
            raise PolicyError(f"policy record: {exc}") from None
        obs_size, action_size = int(record["obs_size"]), int(record["action_size"])
        template = policy_template(cfg, obs_size, action_size)
        stored = serialization.msgpack_restore(record["state"])
        restored = _restore(template, stored, "policy record")
        return cls.create(cfg, restored["params"], restored["obs_stats"], obs_size, action_size)


def policy_template(cfg: Config, obs_size: int, action_size: int) -> dict[str, Any]:
    """Shapes of {"params", "obs_stats"} of a policy (``jax.eval_shape``: nothing is run)."""
    module = _agent_module(cfg)
    params, _, obs_stats = module.learner_template(cfg, obs_size, action_size)
    exported = module.export(params, obs_stats)
    return {"params": exported[_policy_key(cfg)], "obs_stats": obs_stats}


def _policy_key(cfg: Config) -> str:
    return "actor" if cfg.algo == "sac" else "policy"


def _restore(template: Any, stored: Any, where: str) -> Any:
    """``stored`` (a flax state dict) shaped like ``template``, checked leaf by leaf."""
    try:
        restored = serialization.from_state_dict(template, stored)
    except Exception as exc:  # noqa: BLE001 - a missing or extra key
        raise PolicyError(f"{where}: does not match this network ({str(exc).splitlines()[0]})") from None
    flat_t = jax.tree_util.tree_flatten_with_path(template)[0]
    flat_r = jax.tree.leaves(restored)
    if len(flat_t) != len(flat_r):
        raise PolicyError(f"{where}: {len(flat_r)} arrays, this network has {len(flat_t)}")
    for (path, t), r in zip(flat_t, flat_r, strict=True):
        r = np.asarray(r)
        if r.shape != tuple(t.shape) or r.dtype != t.dtype:
            raise PolicyError(
                f"{where}: {jax.tree_util.keystr(path)} is {r.dtype}{list(r.shape)}, "
                f"this network expects {t.dtype}{list(t.shape)}"
            )
    return jax.tree.map(jnp.asarray, restored)


def policy_from_checkpoint(cfg: Config, state_bytes: bytes, obs_size: int, action_size: int) -> PolicyNet:
    """The policy inside a checkpoint's train state (`coherent_jax.run.devices.state_to_bytes`).

    The state is stored as its leaves in tree order, and every trainer's state starts
    with (params, opt_state, obs_stats) (`learner_template`): those leading leaves are
    read, the rest (environments, exploration carry, replay buffer) is left alone.
    """
    module = _agent_module(cfg)
    template = module.learner_template(cfg, obs_size, action_size)
    try:
        stored = serialization.msgpack_restore(state_bytes)
        count = len(jax.tree.leaves(template))
        leaves = [np.asarray(stored[str(i)]) for i in range(count)]
    except Exception as exc:  # noqa: BLE001
        raise PolicyError(f"checkpoint: unreadable state ({str(exc).splitlines()[0]})") from None
    flat = jax.tree_util.tree_flatten_with_path(template)
    for (path, t), leaf in zip(flat[0], leaves, strict=True):
        if leaf.shape != tuple(t.shape) or leaf.dtype != t.dtype:
            raise PolicyError(
                f"checkpoint: {jax.tree_util.keystr(path)} is {leaf.dtype}{list(leaf.shape)}, "
                f"this network expects {t.dtype}{list(t.shape)}"
            )
    params, _, obs_stats = jax.tree_util.tree_unflatten(flat[1], [jnp.asarray(v) for v in leaves])
    exported = module.export(params, obs_stats)
    return PolicyNet.create(cfg, exported[_policy_key(cfg)], obs_stats, obs_size, action_size)


def policy_from_params(cfg: Config, params_bytes: bytes, obs_size: int, action_size: int) -> PolicyNet:
    """The policy in a ``params.msgpack`` (the trainer's ``export_params``, flax serialisation)."""
    module = _agent_module(cfg)
    params, _, obs_stats = module.learner_template(cfg, obs_size, action_size)
    try:
        stored = serialization.msgpack_restore(params_bytes)
    except Exception as exc:  # noqa: BLE001
        raise PolicyError(f"{PARAMS}: unreadable ({str(exc).splitlines()[0]})") from None
    exported = _restore(module.export(params, obs_stats), stored, PARAMS)
    return PolicyNet.create(cfg, exported[_policy_key(cfg)], exported["obs_stats"], obs_size, action_size)


def read_policy(run_dir: Path, obs_size: int, action_size: int) -> tuple[PolicyNet, dict[str, Any]]:
    """The policy of a run directory (a training run's, or one point of a sweep).

    From ``checkpoint.msgpack`` (verified against ``config.yaml``) if there is one, else
    from ``params.msgpack``. Returns (policy, where it came from: {"source", "iteration",
    "env_steps"}; iteration and env_steps are None for ``params.msgpack``, which does not
    record them). Raises `ConfigError`, `coherent_jax.run.checkpoint.CheckpointError` or
    `PolicyError` in one line.
    """
    run_dir = Path(run_dir)
    cfg = load_config(run_dir)
    if (run_dir / CHECKPOINT).is_file():
        ckpt = decode_checkpoint(run_dir / CHECKPOINT, cfg)
        policy = policy_from_checkpoint(cfg, ckpt.state_bytes, obs_size, action_size)
        return policy, {"source": CHECKPOINT, "iteration": ckpt.iteration, "env_steps": ckpt.env_steps}
    if (run_dir / PARAMS).is_file():
        policy = policy_from_params(cfg, (run_dir / PARAMS).read_bytes(), obs_size, action_size)
        return policy, {"source": PARAMS, "iteration": None, "env_steps": None}
    raise PolicyError(f"no {CHECKPOINT} or {PARAMS} in {str(run_dir)!r} (allowed: a run directory)")
