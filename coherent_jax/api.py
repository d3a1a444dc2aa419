"""The Python API: ``coherent_jax.learn(config)`` and ``coherent_jax.load_policy(run_dir)``.

    import coherent_jax

    cfg = coherent_jax.make_config(env="hopper", preset="thesis", explore="coherent")
    result = coherent_jax.learn(cfg)                # or learn({"env": "hopper", ...})
    result.run_dir, result.metrics[-1], result.summary["final_eval_return"]
    action, _ = result.policy.predict(obs)         # numpy in, numpy out, the env's action space
    policy = coherent_jax.load_policy("runs/hopper-...")   # any run directory, later
    coherent_jax.learn(cfg, callbacks=[MyCallback()])      # hooks; one can stop the run

`learn` is ``python -m coherent_jax.train`` called from Python: the same launch path
(`coherent_jax.run.launch.launch_train`: checks, run directory, lock, config, loop, summary),
the same files and lines, the same refusals raised instead of printed. `load_policy` is
`coherent_jax.policy.load_policy`: the policy evaluation acts with (what ``python -m
coherent_jax.evaluate`` reads) as a `Policy`, with ``predict(obs, state,
episode_start, deterministic)`` and actions in the env's own action space.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from coherent_jax.compat import module_getattr
from coherent_jax.config import Config, ConfigError, override_items
from coherent_jax.config.parse import overrides_of
from coherent_jax.policy import Policy, load_policy
from coherent_jax.run.checkpoint import CHECKPOINT, PARAMS
from coherent_jax.run.launch import RUN_SUMMARY, launch_train
from coherent_jax.run.loop_state import StopRequest
from coherent_jax.run.outputs import CallbackLike, checked_callbacks
from coherent_jax.run.rundir import METRICS, read_metrics

#: ``PolicyFunction``, the policy `load_policy` returned before it had ``predict``, is `Policy`.
__getattr__ = module_getattr(__name__, {"PolicyFunction": "coherent_jax.policy.Policy"})


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

    policy: Policy | None
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
    config: Config | Mapping[str, Any] | None = None, callbacks: Sequence[CallbackLike] | None = None
) -> TrainResult:
    """Trains as ``python -m coherent_jax.train`` does and returns the `TrainResult`.

    ``callbacks``: objects with an ``on_iteration`` method (`coherent_jax.CallbackLike`, e.g.
    `coherent_jax.Callback` subclasses) whose hooks the run calls (`coherent_jax.run.outputs`:
    ``on_iteration`` with each metrics row, which can stop the run with a checkpoint, and where
    the object has them ``on_start``, ``on_evaluation``, ``on_end``).

    ``config`` is a `Config` (`make_config`) or a mapping of overrides
    (``{"env": "hopper", "ppo.clip_eps": 0.1}``, a group's keys dotted or nested);
    ``{"resume": run_dir}`` continues a run. Raises, before anything is written,
    `ConfigError` (a bad key or value, a busy or unusable run directory),
    `coherent_jax.run.checkpoint.CheckpointError` (a checkpoint that does not fit) or
    `coherent_jax.run.outputs.TrackingError` (``wandb=true`` without ``wandb``); raises
    `coherent_jax.run.loop_state.DivergenceError` when the run diverges (its last good
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
    if summary is None and (run_dir / RUN_SUMMARY).is_file():  # already complete
        summary = json.loads((run_dir / RUN_SUMMARY).read_text())
    has_policy = (run_dir / CHECKPOINT).is_file() or (run_dir / PARAMS).is_file()
    return TrainResult(
        policy=load_policy(run_dir) if has_policy else None,
        metrics=read_metrics(run_dir / METRICS),
        run_dir=run_dir,
        summary=summary,
        stopped_by=summary["stopped_by"] if summary is not None else stop.name,
    )
