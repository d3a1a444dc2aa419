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
even by SIGKILL, from any working directory, after the directory was moved): the
rows past the checkpoint are dropped and recomputed, so the metrics equal those of
an uninterrupted run of the same seed; ``resume=RUN_DIR total_steps=N`` extends a
finished run. While it trains, a run holds ``run.lock`` in its directory
(`coherent_jax.runlock`): a second process starting or resuming there is refused. Before
anything is written, a key given twice, a configuration whose arrays cannot fit in
memory (`coherent_jax.memory`), a sweep's directory given to ``resume=`` and a run whose
``metrics.jsonl`` lost rows before its checkpoint are refused like any bad input.
A non-finite loss or parameter stops the run (exit status 3) naming
the iteration and the quantity; the last good checkpoint stays. The loop itself is
`coherent_jax.loop`, shared with sweeps. Exit statuses: 0 done, 2 bad input,
3 diverged, 4 another process of a ``distributed=true`` run failed (resumable; see
`coherent_jax.distributed`), 128 + signal number when stopped by SIGINT/SIGTERM
(resumable).
"""

from __future__ import annotations

import contextlib
import json
import signal
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from coherent_jax import cli, distributed, rundir, runlock
from coherent_jax.config import Config, ConfigError, help_text, parse_overrides
from coherent_jax.loop import (
    PREFIX,
    DivergenceError,
    Job,
    StopRequest,
    quiet_imports,
    run_command,
    run_loop,
    to_float,
)
from coherent_jax.memory import check_memory
from coherent_jax.runs import (
    METRICS,
    Checkpoint,
    CheckpointError,
    atomic_write,
    load_config,
    prepare_output_dir,
    record_versions,
    resume_config,
    resume_point,
    split_resume,
    write_config,
)

EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 3


def default_run_dir(cfg: Config) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{cfg.env}-{cfg.algo}-{cfg.explore}-s{cfg.seed}-{stamp}"


def train(
    cfg: Config,
    run_dir: Path | None = None,
    progress_fn: Callable[[int, dict[str, float]], None] | None = None,
    resume: Checkpoint | None = None,
    stop: StopRequest | None = None,
) -> dict[str, Any]:
    """Runs training for ``cfg``; returns the summary (also written to ``run_dir``).

    ``progress_fn(iteration, metrics)`` receives every iteration's metrics (as
    Python floats), in the manner of Brax's trainers. With `resume` (a verified
    checkpoint of ``run_dir``) the run continues after the checkpoint's iteration.
    Raises `DivergenceError` when a loss or a parameter becomes non-finite. The
    summary's ``stopped_by`` names the signal when SIGINT/SIGTERM ended the run early.
    """
    import jax

    from coherent_jax.agents import make_trainer
    from coherent_jax.loop import write_params

    job = Job(
        cfg=cfg,
        trainer=make_trainer(cfg),
        seeds=[cfg.seed],
        names=[run_dir.name if run_dir else "run"],
        run_dir=run_dir,
        point_dirs=[run_dir] if run_dir else [],
        label=f"{cfg.env} {cfg.algo} explore={cfg.explore}",
    )
    with contextlib.ExitStack() as stack:
        stop = stop or stack.enter_context(StopRequest())
        out = run_loop(job, stop, resume, progress_fn)
    total_steps = out.done * cfg.steps_per_iteration
    last_eval = {k: v[0] for k, v in out.last_eval.items()}
    summary = {
        "env": cfg.env,
        "algo": cfg.algo,
        "explore": cfg.explore,
        "seed": cfg.seed,
        "env_steps": total_steps,
        "iterations": out.done,
        "final_eval_return": last_eval.get("eval/episode_return"),
        "final_eval_return_std": last_eval.get("eval/episode_return_std"),
        "final_train_return": to_float(out.last_return[0]),
        "compile_s": round(out.compile_s, 2),
        "train_s": round(out.loop.train_s, 2),
        "eval_s": round(out.loop.eval_s, 2),
        "wall_s": round(out.wall_s, 2),
        "train_env_steps_per_s": round(total_steps / max(out.loop.train_s, 1e-9), 1),
        "jax_version": jax.__version__,
        "backend": jax.default_backend(),
        "num_devices": out.num_devices,
        "resumed_from": out.start if resume is not None else None,
        "stopped_by": out.stopped_by,
        "physics": out.physics,
    }
    if out.stopped_by is not None:
        print(
            f"{PREFIX} stopped by {out.stopped_by} after iteration {out.done}; "
            + (f"checkpoint saved; continue with resume={run_dir}" if run_dir else "nothing saved"),
            flush=True,
        )
        return summary
    write_params(job.trainer, out.state, [run_dir] if run_dir else [], points=False)  # every process
    if run_dir:
        atomic_write(run_dir / "summary.json", json.dumps(summary, indent=2).encode())
    final = summary["final_eval_return"]
    print(
        f"{PREFIX} done: eval return {final if final is None else round(final, 1)}, "
        f"{summary['train_env_steps_per_s']:.0f} env steps/s training, compile {out.compile_s:.1f} s, "
        f"wall {summary['wall_s']:.0f} s" + (f"; run dir {run_dir}" if run_dir else ""),
        flush=True,
    )
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    return run_command(list(sys.argv[1:] if argv is None else argv), help_text, _main)


def _main(argv: list[str], stop: StopRequest) -> int:
    from coherent_jax.parallel import check_devices

    resume_dir, rest = split_resume(argv)
    checkpoint, lock = None, None
    try:
        cli.check_unique(argv)
        if resume_dir is not None:
            rundir.refuse_sweep_for_train(Path(resume_dir))
            cfg, run_dir = resume_config(resume_dir, rest)
            if distributed.needs_supervisor(cfg.distributed):
                return distributed.supervise("coherent_jax.train", argv)
            # Several hosts: every process reads the checkpoint, only process 0 writes.
            is_writer = check_devices(cfg)
            check_memory(cfg)
            checkpoint = resume_point(run_dir, cfg)
            if checkpoint is not None:
                finished = checkpoint.iteration >= cfg.num_iterations and (run_dir / "summary.json").exists()
                rundir.check_metrics([run_dir / METRICS], checkpoint.iteration, finished)
                if finished:
                    print(f"{PREFIX} {run_dir} is already complete ({checkpoint.iteration} iterations)")
                    return 0
            run_dir = run_dir if is_writer else None
            lock = runlock.acquire(run_dir, "resume") if run_dir else None
        else:
            cfg = parse_overrides(argv)
            if distributed.needs_supervisor(cfg.distributed):
                return distributed.supervise("coherent_jax.train", argv)
            is_writer = check_devices(cfg)  # several hosts: only process 0 writes
            check_memory(cfg)
            path = Path(cfg.run_dir) if cfg.run_dir else default_run_dir(cfg)
            run_dir = None
            if is_writer:
                runlock.refuse_if_held(path, "run_dir")
                run_dir = prepare_output_dir(path)
                lock = runlock.acquire(run_dir, "run_dir")
    except (ConfigError, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    with lock or contextlib.nullcontext():
        return _run(cfg, run_dir, resume_dir, checkpoint, stop)


def _run(cfg: Config, run_dir: Path | None, resume_dir: str | None, checkpoint, stop: StopRequest) -> int:
    """Writes the run's config and versions, trains, and returns the exit status (the input checked)."""
    if run_dir:
        if resume_dir is None:
            write_config(run_dir, cfg)
        elif cfg.total_steps != load_config(run_dir).total_steps:
            write_config(run_dir, cfg)  # an extended budget is the run's own from now on
        record_versions(run_dir, None if resume_dir is None else (checkpoint.iteration if checkpoint else 0))
        print(f"{PREFIX} run dir {run_dir}", flush=True)
    if stop.signum is not None:
        print(f"{PREFIX} stopped by {stop.name} before training started", flush=True)
        return 128 + stop.signum
    quiet_imports()
    try:
        summary = train(cfg, run_dir, resume=checkpoint, stop=stop)
    except CheckpointError as exc:  # a state that does not fit this trainer, found on restoring it
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    except DivergenceError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return EXIT_DIVERGED
    if summary["stopped_by"] is not None:
        return 128 + int(signal.Signals[summary["stopped_by"]])
    return 0


if __name__ == "__main__":
    sys.exit(distributed.run_cli(main))
