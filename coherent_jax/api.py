"""The Python API: ``coherent_jax.learn(config)`` and ``coherent_jax.load_policy(run_dir)``.

    import coherent_jax

    cfg = coherent_jax.make_config(env="hopper", preset="thesis", explore="coherent")
    result = coherent_jax.learn(cfg)                # or learn({"env": "hopper", ...})
    result.run_dir, result.metrics[-1], result.summary["final_eval_return"]
    action = result.policy(obs)                     # numpy in, numpy out
    policy = coherent_jax.load_policy("runs/hopper-...")   # any run directory, later
    coherent_jax.learn(cfg, callbacks=[MyCallback()])      # hooks; one can stop the run

`learn` is ``python -m coherent_jax.train`` called from Python: the same launch path
(`coherent_jax.run.single.launch_train`: checks, run directory, lock, config, loop, summary), the same
files and lines, the same refusals raised instead of printed. `load_policy` is the
policy evaluation acts with (`coherent_jax.run.policy.load_policy`, what ``python -m
coherent_jax.evaluate`` reads), as a plain function of observations.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from coherent_jax.config import Config, ConfigError, override_items
from coherent_jax.config.legacy import overrides_of
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.run.callbacks import Callback
from coherent_jax.run.callbacks import checked as checked_callbacks
from coherent_jax.run.policy import load_policy as read_policy
from coherent_jax.run.runs import CHECKPOINT, METRICS, PARAMS, load_config, read_metrics
from coherent_jax.run.single import SUMMARY, launch_train
from coherent_jax.run.stop import StopRequest


class PolicyFunction:
    """A trained policy as a function of observations: obs [o] or [n, o] -> action [p] or [n, p].

    The deterministic (mean) action evaluation takes: the observation normalised with the
    run's statistics (when it normalised them), the algorithm's mean (A2C/PPO: the
    strategy's mean action; SAC: tanh of the actor's mean), clipped to [-1, 1] as every
    task's ``VecEnv.step`` clips it. Those are the task's actions; the task itself maps
    them onto its actuators' range. Needs JAX: the network is the run's Flax module,
    called through one jitted function (compiled on the first call, and again for each
    new batch shape). ``policy`` is the `coherent_jax.run.policy.Policy` underneath (for
    ``Policy.sample`` or to use it inside JAX code); ``origin`` says where it was read
    from (``source``, ``iteration``, ``env_steps``).
    """

    def __init__(self, policy: Any, origin: dict[str, Any]) -> None:
        self.policy = policy
        self.origin = origin
        self._act = jax.jit(lambda p, obs: jnp.clip(p.mean_action(obs), -1.0, 1.0))

    @property
    def obs_size(self) -> int:
        return self.policy.obs_size

    @property
    def action_size(self) -> int:
        return self.policy.action_size

    def __call__(self, obs: Any) -> Any:
        x = np.asarray(obs, np.float32)
        if x.ndim not in (1, 2) or x.shape[-1] != self.obs_size:
            raise ValueError(
                f"invalid observation of shape {list(x.shape)} "
                f"(allowed: [{self.obs_size}] or [n, {self.obs_size}])"
            )
        return np.asarray(self._act(self.policy, x))


def load_policy(run_dir: str | Path) -> PolicyFunction:
    """The policy of a run directory (a training run's or a sweep point's) as obs -> action.

    Read from ``checkpoint.msgpack`` (verified against ``config.yaml``), else from
    ``params.msgpack``, as ``python -m coherent_jax.evaluate`` reads it; see
    `PolicyFunction` for what the action is. Needs JAX (the policy is the run's Flax
    module). Raises `ConfigError`, `coherent_jax.run.runs.CheckpointError` or
    `coherent_jax.run.policy.PolicyError` in one line for a directory that holds no usable policy.
    """
    run_dir = Path(run_dir)
    cfg = load_config(run_dir)
    env = VecEnv(cfg.env, 1, cfg.episode_length, cfg.physics, cfg.physics_threads)  # its sizes
    policy, origin = read_policy(run_dir, env.observation_size, env.action_size)
    return PolicyFunction(policy, origin)


class TrainResult(NamedTuple):
    """What `learn` returns.

    Attributes:
      policy: the final policy (`load_policy` of the run directory); None if the run was
        stopped (SIGINT/SIGTERM) before it saved any checkpoint.
      metrics: the rows of ``metrics.jsonl`` as logged, one per iteration (``eval/*`` on
        evaluation rows; None where a value was not finite).
      run_dir: the run directory.
      summary: ``summary.json`` (its ``stopped_by`` names the signal of a run stopped
        early, which ``resume=run_dir`` continues); None if it stopped before training.
      stopped_by: None for a run that finished its budget; the signal's name (``"SIGINT"``,
        ``"SIGTERM"``) or ``"callback"`` (the summary's ``stop_reason`` says why) for one
        stopped early, which ``{"resume": run_dir}`` continues.
    """

    policy: PolicyFunction | None
    metrics: list[dict[str, Any]]
    run_dir: Path
    summary: dict[str, Any] | None
    stopped_by: str | None = None


def _items(config: Config | Mapping[str, Any] | None) -> list[str]:
    """The ``key=value`` items of `config`, as the command line would give them."""
    if config is None:
        return []
    if isinstance(config, Config):
        return override_items(overrides_of(config))
    if isinstance(config, Mapping):
        return override_items(config)
    raise ConfigError(
        f"invalid config {config!r}: a {type(config).__name__} "
        "(allowed: a coherent_jax.Config or a mapping of config keys to values)"
    )


def learn(
    config: Config | Mapping[str, Any] | None = None, callbacks: Sequence[Callback] | None = None
) -> TrainResult:
    """Trains as ``python -m coherent_jax.train`` does and returns the `TrainResult`.

    ``callbacks``: `coherent_jax.Callback` instances whose hooks the run calls
    (`coherent_jax.run.callbacks`: ``on_start``, ``on_iteration`` with each metrics row,
    which can stop the run with a checkpoint, ``on_evaluation``, ``on_end``).

    ``config`` is a `Config` (`make_config`) or a mapping of overrides
    (``{"env": "hopper", "ppo.clip_eps": 0.1}``, a group's keys dotted or nested);
    ``{"resume": run_dir}`` continues a run. Raises, before anything is written,
    `ConfigError` (a bad key or value, a busy or unusable run directory),
    `coherent_jax.run.runs.CheckpointError` (a checkpoint that does not fit) or
    `coherent_jax.run.tracking.TrackingError` (``wandb=true`` without ``wandb``); raises
    `coherent_jax.run.divergence.DivergenceError` when the run diverges (its last good
    checkpoint stays). ``distributed=true`` runs from the command line only. SIGINT and
    SIGTERM stop the run after the current iteration, with a checkpoint.
    """
    items = _items(config)
    hooks = checked_callbacks(callbacks)
    distributed = config.distributed if isinstance(config, Config) else (config or {}).get("distributed")
    if distributed:
        raise ConfigError(
            f"invalid value for 'distributed': {distributed!r} in coherent_jax.learn "
            "(allowed: false; several hosts run python -m coherent_jax.train distributed=true)"
        )
    with StopRequest() as stop:
        done = launch_train(items, stop, hooks)
    run_dir = done.run_dir
    summary = done.summary
    if summary is None and (run_dir / SUMMARY).is_file():  # already complete
        summary = json.loads((run_dir / SUMMARY).read_text())
    has_policy = (run_dir / CHECKPOINT).is_file() or (run_dir / PARAMS).is_file()
    return TrainResult(
        policy=load_policy(run_dir) if has_policy else None,
        metrics=read_metrics(run_dir / METRICS),
        run_dir=run_dir,
        summary=summary,
        stopped_by=summary["stopped_by"] if summary is not None else stop.name,
    )
