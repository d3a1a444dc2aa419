"""Command-line training: ``python -m coherent_jax.train env=halfcheetah algo=ppo ...``.

Overrides are ``key=value`` (``--help`` lists them all). A bad override is
reported in one line and exits with status 2 before anything is written. A run
writes one directory:

* ``config.yaml`` (resolved config) and ``versions.json`` (Python, platform, package
  versions);
* ``metrics.jsonl`` (one row per iteration, with ``eval/*`` on evaluation rows) and,
  with ``tensorboard=true``, the same scalars as TensorBoard event files in ``tb/``;
* ``checkpoint.msgpack`` (the whole train state and the loop's state, every
  ``checkpoint_every`` iterations, at the end and when stopped by SIGINT/SIGTERM;
  see `coherent_jax.runs`);
* at the end ``params.msgpack`` (final parameters and observation statistics, flax
  serialisation) and ``summary.json``.

``resume=RUN_DIR`` continues a run from its checkpoint (a run killed at any moment,
even by SIGKILL): the rows past the checkpoint are dropped and recomputed, so the
metrics equal those of an uninterrupted run of the same seed. A non-finite loss or
parameter stops the run (exit status 3) naming the iteration and the quantity; the
last good checkpoint stays. Exit statuses: 0 done, 2 bad input, 3 diverged,
128 + signal number when stopped by SIGINT/SIGTERM (resumable).
"""

from __future__ import annotations

import dataclasses
import json
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from coherent_jax import distributed
from coherent_jax.config import Config, ConfigError, help_text, parse_overrides, to_dict
from coherent_jax.runs import (
    CHECKPOINT,
    CONFIG,
    METRICS,
    VERSIONS,
    Checkpoint,
    CheckpointError,
    LoopState,
    atomic_write,
    config_difference,
    decode_checkpoint,
    encode_checkpoint,
    load_config,
    package_versions,
    restore_state,
    state_to_bytes,
    truncate_metrics,
)

EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 3


class DivergenceError(RuntimeError):
    """A loss or a parameter became non-finite; the message names the iteration and the quantity."""


def default_run_dir(cfg: Config) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{cfg.env}-{cfg.algo}-{cfg.explore}-s{cfg.seed}-{stamp}"


def prepare_run_dir(cfg: Config) -> Path:
    """Creates the run directory; refuses one that already holds files."""
    path = Path(cfg.run_dir) if cfg.run_dir else default_run_dir(cfg)
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise ConfigError(f"invalid value for 'run_dir': {str(path)!r} (allowed: a new or empty directory)")
    path.mkdir(parents=True, exist_ok=True)
    return path


def _to_float(x: Any) -> float | None:
    value = float(x)
    return value if math.isfinite(value) else None


def run_keys(seed: int):
    """(key, init_key) of a run: ``init_key`` starts the state, ``key`` is split once per evaluation.

    Sweeps derive each grid point's keys with this same function, so a point equals
    the single run with its settings.
    """
    import jax

    key = jax.random.PRNGKey(seed)
    key, init_key = jax.random.split(key)
    return key, init_key


def _first_non_finite(tree: Any) -> str:
    """Path of the first array of `tree` (on the host) holding a NaN or an infinity."""
    import jax
    import numpy as np

    for where, leaf in jax.tree_util.tree_flatten_with_path(jax.device_get(tree))[0]:
        leaf = np.asarray(leaf)
        if np.issubdtype(leaf.dtype, np.inexact) and not np.all(np.isfinite(leaf)):
            return jax.tree_util.keystr(where)
    return "?"


class _StopRequest:
    """Turns SIGINT/SIGTERM into a request to stop after the current iteration."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> _StopRequest:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is not None:  # a second signal: stop at once
            signal.signal(signum, self._previous.get(signum, signal.SIG_DFL))
            signal.raise_signal(signum)
            return
        self.signum = signum
        print(
            f"\n[coherent_jax] {signal.Signals(signum).name}: stopping after the current iteration",
            file=sys.stderr,
            flush=True,
        )

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def train(
    cfg: Config,
    run_dir: Path | None = None,
    progress_fn: Callable[[int, dict[str, float]], None] | None = None,
    resume: Checkpoint | None = None,
) -> dict[str, Any]:
    """Runs training for ``cfg``; returns the summary (also written to ``run_dir``).

    ``progress_fn(iteration, metrics)`` receives every iteration's metrics (as
    Python floats), in the manner of Brax's trainers. With `resume` (a verified
    checkpoint of ``run_dir``) the run continues after the checkpoint's iteration.
    Raises `DivergenceError` when a loss or a parameter becomes non-finite. The
    summary's ``stopped_by`` names the signal when SIGINT/SIGTERM ended the run early.
    """
    import jax
    import jax.numpy as jnp
    from flax import serialization
    from tqdm.auto import tqdm

    from coherent_jax import distributed, parallel
    from coherent_jax.agents import make_trainer

    t_start = time.perf_counter()
    num_devices = parallel.resolve_num_devices(cfg.num_devices)
    parallel.check_env_split(cfg.num_envs, num_devices)
    trainer = make_trainer(cfg)
    key, init_key = run_keys(cfg.seed)
    loop = LoopState(eval_key=[int(w) for w in jax.device_get(key)])
    start = 0
    if resume is None:
        state, shardings = parallel.init_state(trainer, init_key, num_devices, cfg.num_envs)
    else:  # the state's structure from tracing init, its values from the checkpoint
        template = jax.eval_shape(trainer.init, init_key)
        state = restore_state(template, resume.state_bytes, Path(cfg.resume or run_dir or ".") / CHECKPOINT)
        state, shardings = parallel.shard_state(state, num_devices, cfg.num_envs)
        loop, start = resume.loop, resume.iteration
        key = jnp.asarray(loop.eval_key, dtype=jnp.uint32)

    def params_finite(s):
        leaves = jax.tree.leaves(trainer.export_params(s))
        return jnp.all(
            jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves if jnp.issubdtype(x.dtype, jnp.inexact)])
        )

    # The engine `physics=auto` resolved to (trainers keep their training env in `.env`).
    physics = getattr(getattr(trainer, "env", None), "physics", cfg.physics)

    t0 = time.perf_counter()
    iteration = parallel.compile_iteration(trainer, state, shardings)
    evaluate = jax.jit(trainer.evaluate).lower(state, key).compile()
    check_params = jax.jit(params_finite).lower(state).compile()
    compile_s = time.perf_counter() - t0
    print(
        f"[coherent_jax] {cfg.env} {cfg.algo} explore={cfg.explore} physics={physics}: "
        f"compiled in {compile_s:.1f} s; "
        f"{cfg.num_iterations} iterations of {cfg.steps_per_iteration} env steps"
        + (f" on {num_devices} devices" if num_devices > 1 else "")
        + (f"; resuming after iteration {start}" if resume is not None else ""),
        flush=True,
    )

    def save_checkpoint(done: int) -> None:
        loop.eval_key = [int(w) for w in jax.device_get(key)]
        loop.elapsed_s = elapsed_before + time.perf_counter() - t_start
        state_bytes = state_to_bytes(state)  # every process: the state is gathered from all
        if not run_dir:
            return
        blob = encode_checkpoint(cfg, done, done * cfg.steps_per_iteration, loop, state_bytes)
        atomic_write(run_dir / CHECKPOINT, blob)
        if writer is not None:
            writer.flush()

    # Several processes: only process 0 has the run directory, but all gather the state.
    checkpoints = distributed.from_writer(run_dir is not None)

    elapsed_before = loop.elapsed_s
    metrics_file = writer = None
    if run_dir:
        if resume is not None:
            truncate_metrics(run_dir / METRICS, start)
        metrics_file = open(run_dir / METRICS, "a" if resume is not None else "w")
        if cfg.tensorboard:
            from tensorboardX import SummaryWriter

            # purge_step hides events a killed run wrote past the checkpoint.
            purge = start * cfg.steps_per_iteration + 1 if resume is not None else None
            writer = SummaryWriter(str(run_dir / "tb"), purge_step=purge, flush_secs=30)
    bar = tqdm(
        total=cfg.num_iterations * cfg.steps_per_iteration,
        initial=start * cfg.steps_per_iteration,
        unit="step",
        disable=not cfg.progress or not distributed.is_writer(),  # one progress bar per run
        dynamic_ncols=True,
        mininterval=1.0,
    )
    done = saved = start
    stopper = _StopRequest()
    try:
        with stopper:
            for i in range(start, cfg.num_iterations):
                t0 = time.perf_counter()
                state, metrics = iteration(state)
                metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
                finite = bool(check_params(state))
                loop.train_s += time.perf_counter() - t0
                _check_finite(i + 1, metrics, finite, state, trainer, run_dir, saved)
                last = i == cfg.num_iterations - 1
                if last or (cfg.eval_every > 0 and (i + 1) % cfg.eval_every == 0):
                    t0 = time.perf_counter()
                    key, eval_key = jax.random.split(key)
                    loop.last_eval = {
                        k: float(v) for k, v in jax.device_get(evaluate(state, eval_key)).items()
                    }
                    loop.eval_s += time.perf_counter() - t0
                    metrics.update(loop.last_eval)
                if not math.isnan(metrics["train/episode_return"]):
                    loop.last_return = metrics["train/episode_return"]
                env_steps = (i + 1) * cfg.steps_per_iteration
                row = {
                    "iteration": i + 1,
                    "env_steps": env_steps,
                    "time_s": elapsed_before + time.perf_counter() - t_start,
                }
                row.update({k: _to_float(v) for k, v in metrics.items()})
                if metrics_file:
                    metrics_file.write(json.dumps(row) + "\n")
                    metrics_file.flush()
                if writer is not None:
                    for k, v in metrics.items():
                        if math.isfinite(v):
                            writer.add_scalar(k, v, env_steps)
                done = i + 1
                if progress_fn:
                    progress_fn(i + 1, metrics)
                # A signal to one process stops all of them after this same iteration; the
                # agreed value, not the local one, decides (a signal may arrive meanwhile).
                stopping = distributed.largest(stopper.signum or 0)
                every = cfg.checkpoint_every > 0 and done % cfg.checkpoint_every == 0
                if checkpoints and (last or every or stopping):
                    save_checkpoint(done)
                    saved = done
                bar.update(cfg.steps_per_iteration)
                bar.set_postfix(
                    sps=f"{env_steps / max(loop.train_s, 1e-9):.0f}",
                    ret=f"{loop.last_return:.1f}",
                    eval=f"{loop.last_eval.get('eval/episode_return', float('nan')):.1f}",
                    refresh=False,
                )
                if stopping:
                    stopper.signum = stopper.signum or stopping
                    break
    finally:
        bar.close()
        if metrics_file:
            metrics_file.close()
        if writer is not None:
            writer.close()

    total_steps = done * cfg.steps_per_iteration
    summary = {
        "env": cfg.env,
        "algo": cfg.algo,
        "explore": cfg.explore,
        "seed": cfg.seed,
        "env_steps": total_steps,
        "iterations": done,
        "final_eval_return": loop.last_eval.get("eval/episode_return"),
        "final_eval_return_std": loop.last_eval.get("eval/episode_return_std"),
        "final_train_return": _to_float(loop.last_return),
        "compile_s": round(compile_s, 2),
        "train_s": round(loop.train_s, 2),
        "eval_s": round(loop.eval_s, 2),
        "wall_s": round(elapsed_before + time.perf_counter() - t_start, 2),
        "train_env_steps_per_s": round(total_steps / max(loop.train_s, 1e-9), 1),
        "jax_version": jax.__version__,
        "backend": jax.default_backend(),
        "num_devices": num_devices,
        "resumed_from": start if resume is not None else None,
        "stopped_by": signal.Signals(stopper.signum).name if stopper.signum is not None else None,
        "physics": physics,
    }
    if stopper.signum is not None:
        print(
            f"[coherent_jax] stopped by {summary['stopped_by']} after iteration {done}; "
            + (f"checkpoint saved; continue with resume={run_dir}" if run_dir else "nothing saved"),
            flush=True,
        )
        return summary
    payload = distributed.to_host(trainer.export_params(state))
    if run_dir:
        atomic_write(run_dir / "params.msgpack", serialization.to_bytes(payload))
        atomic_write(run_dir / "summary.json", json.dumps(summary, indent=2).encode())
    final = summary["final_eval_return"]
    print(
        f"[coherent_jax] done: eval return {final if final is None else round(final, 1)}, "
        f"{summary['train_env_steps_per_s']:.0f} env steps/s training, compile {compile_s:.1f} s, "
        f"wall {summary['wall_s']:.0f} s" + (f"; run dir {run_dir}" if run_dir else ""),
        flush=True,
    )
    return summary


def _check_finite(
    it: int,
    metrics: dict[str, float],
    params_ok: bool,
    state: Any,
    trainer: Any,
    run_dir: Path | None,
    saved: int,
) -> None:
    """Raises `DivergenceError` if a loss metric or a parameter is non-finite.

    Losses are checked only when the iteration applied an update
    (``train/updates_applied`` > 0, or absent): SAC reports NaN losses by design while
    its replay buffer warms up. Parameters are always checked. `saved` is the
    iteration of the last checkpoint written (the one a resume starts from).
    """
    updated = metrics.get("train/updates_applied", 1.0) > 0
    bad = [k for k, v in metrics.items() if updated and "loss" in k and not math.isfinite(v)]
    if not bad and params_ok:
        return
    if bad:
        quantity = f"{bad[0]} = {metrics[bad[0]]}"
    else:
        quantity = f"parameter {_first_non_finite(trainer.export_params(state))} is not finite"
    kept = (
        f"; last good checkpoint: iteration {saved} in {run_dir / CHECKPOINT}"
        if run_dir and (run_dir / CHECKPOINT).exists()
        else "; no checkpoint was written before it"
    )
    raise DivergenceError(f"diverged at iteration {it}: {quantity}{kept}")


def _resume_config(resume_dir: str, overrides: list[str]) -> tuple[Config, Path]:
    """The run's stored config with `overrides`, refused if they change what it computes."""
    path = Path(resume_dir)
    if not resume_dir or not path.is_dir():
        raise ConfigError(
            f"invalid value for 'resume': {resume_dir!r} (allowed: an existing run directory with {CONFIG} "
            f"and {CHECKPOINT})"
        )
    stored = load_config(path)
    cfg = parse_overrides(overrides, base=stored)
    changed = config_difference(cfg, stored)
    if changed is not None:
        raise ConfigError(
            f"invalid value for {changed!r} with resume: {getattr(cfg, changed)!r} "
            f"(allowed: the run's own value {getattr(stored, changed)!r})"
        )
    if cfg.run_dir and Path(cfg.run_dir).resolve() != path.resolve():
        raise ConfigError(
            f"invalid value for 'run_dir' with resume: {cfg.run_dir!r} (allowed: {resume_dir!r})"
        )
    return dataclasses.replace(cfg, run_dir=str(path), resume=resume_dir), path


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "help") for a in argv):
        print(help_text())
        return 0
    resume_args = [a for a in argv if a.split("=", 1)[0].strip() == "resume"]
    rest = [a for a in argv if a not in resume_args]
    checkpoint = None
    try:
        if resume_args and resume_args[-1].split("=", 1)[1].strip():
            cfg, run_dir = _resume_config(resume_args[-1].split("=", 1)[1].strip(), rest)
            if distributed.needs_supervisor(cfg.distributed):
                return distributed.supervise("coherent_jax.train", argv)
            # Several hosts: every process reads the checkpoint, only process 0 writes.
            is_writer = check_devices(cfg)
            checkpoint = decode_checkpoint(run_dir / CHECKPOINT, cfg)
            if checkpoint.iteration >= cfg.num_iterations and (run_dir / "summary.json").exists():
                print(f"[coherent_jax] {run_dir} is already complete ({checkpoint.iteration} iterations)")
                return 0
            run_dir = run_dir if is_writer else None
        else:
            cfg = parse_overrides(argv)
            if distributed.needs_supervisor(cfg.distributed):
                return distributed.supervise("coherent_jax.train", argv)
            is_writer = check_devices(cfg)  # several hosts: only process 0 writes
            run_dir = prepare_run_dir(cfg) if is_writer else None
    except (ConfigError, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if checkpoint is None:
        from omegaconf import OmegaConf

        if run_dir:
            atomic_write(run_dir / CONFIG, OmegaConf.to_yaml(to_dict(cfg)).encode())
            atomic_write(run_dir / VERSIONS, json.dumps(package_versions(), indent=2).encode())
    elif run_dir:
        versions = package_versions()
        stored = json.loads((run_dir / VERSIONS).read_text()) if (run_dir / VERSIONS).exists() else {}
        if {k: v for k, v in versions.items() if k != "platform"} != {
            k: v for k, v in stored.items() if k != "platform"
        }:
            name = f"versions-resumed-{checkpoint.iteration}.json"
            atomic_write(run_dir / name, json.dumps(versions, indent=2).encode())
            print(f"[coherent_jax] warning: package versions differ from the run's; see {name}", flush=True)
    if run_dir:
        print(f"[coherent_jax] run dir {run_dir}", flush=True)
    try:
        summary = train(cfg, run_dir, resume=checkpoint)
    except DivergenceError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return EXIT_DIVERGED
    if summary["stopped_by"] is not None:
        return 128 + int(signal.Signals[summary["stopped_by"]])
    return 0


def check_devices(cfg: Config, split_envs: bool = True) -> bool:
    """Initialises multi-host JAX if asked and checks the device split before anything is written.

    Returns whether this process writes the outputs (process 0 of a distributed run).
    """
    from coherent_jax import parallel

    parallel.maybe_initialize_distributed(cfg.distributed)
    num_devices = parallel.resolve_num_devices(cfg.num_devices)
    if split_envs:
        parallel.check_env_split(cfg.num_envs, num_devices)
        distributed.check_device_split(num_devices)
    return distributed.is_writer()


if __name__ == "__main__":
    sys.exit(distributed.run_cli(main))
