"""A single run: `launch_train`, what ``python -m coherent_jax.train`` and `coherent_jax.learn`
run, and `train`, its body (build the trainer, drive the loop, write the parameters and
``summary.json``), also called directly by tests and experiments.

`launch_train` reads top down: parse (or read a resumed run's config), check, prepare the run
directory, then `train`, then the exit status; the steps it shares with a sweep are the helpers
of `coherent_jax.run.launch`.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from coherent_jax.config import Config, cli, parse_overrides
from coherent_jax.envs.registry import task_label
from coherent_jax.run import callbacks as hooks
from coherent_jax.run import launch, rundir, tracking
from coherent_jax.run.callbacks import Callback, StartInfo
from coherent_jax.run.launch import Launched
from coherent_jax.run.loop_state import Job, Outcome, to_float
from coherent_jax.run.runs import (
    METRICS,
    PREFIX,
    Checkpoint,
    atomic_write,
    config_text,
    load_config,
    resume_config,
    resume_point,
    split_resume,
    stored_config,
    write_config,
)
from coherent_jax.run.stop import StopRequest

MODULE = "coherent_jax.train"  # ``python -m MODULE``, which the supervisor of a distributed run starts
SUMMARY = "summary.json"  # written last: a resumed run holding it (and at its budget) is complete


def read_plan(argv: Sequence[str]) -> tuple[Config, Path | None]:
    """The config of `argv` and, for ``resume=DIR``, the run directory (its stored config with
    the other items as overrides); raises `ConfigError` naming the bad item."""
    resume_dir, rest = split_resume(list(argv))
    cli.check_unique(list(argv))
    if resume_dir is None:
        return parse_overrides(list(argv)), None
    rundir.refuse_sweep_for_train(Path(resume_dir))
    return resume_config(resume_dir, rest)


def check_train(cfg: Config) -> bool:
    """The devices and the memory; returns whether this process writes the outputs."""
    from coherent_jax.run.memory import check_memory  # lazy: JAX; --help and dry runs go without
    from coherent_jax.run.sharding import check_devices  # lazy: as check_memory

    is_writer = check_devices(cfg)  # several hosts: only process 0 writes
    check_memory(cfg)
    return is_writer


def describe_train(argv: Sequence[str]) -> str:
    """What a dry run prints: the resolved config as ``config.yaml`` would hold it, and where the
    run would write. Parsed and checked as a run's input is; nothing is created or written, and
    the devices, the memory and the run directory are not checked."""
    cfg, run_dir = read_plan(argv)
    launch.warn(cfg)
    return (
        config_text(cfg).rstrip()
        + "\n"
        + launch.where(cfg, run_dir, default_run_dir(cfg), run_dir is not None)
    )


def launch_train(argv: Sequence[str], stop: StopRequest, callbacks: Sequence[Callback] = ()) -> Launched:
    """Runs the command line `argv` of ``python -m coherent_jax.train``: parse, check, prepare
    the run directory, train (with `callbacks`, from the Python API), exit status.

    Raises one of `launch.REFUSED` (bad input before anything is written, or on restoring a
    state that does not fit; a divergence).
    """
    cfg, resume_dir = read_plan(argv)
    supervised = launch.preflight(cfg, MODULE, argv)
    if supervised is not None:
        return Launched(supervised, None, None)
    is_writer = check_train(cfg)
    if resume_dir is None:
        held = launch.hold_new(Path(cfg.run_dir) if cfg.run_dir else default_run_dir(cfg), is_writer)
    else:
        checkpoint = resume_point(resume_dir, cfg)
        finished = launch.is_complete(resume_dir, checkpoint, cfg, SUMMARY)
        if checkpoint is not None:
            rundir.check_metrics([resume_dir / METRICS], checkpoint.iteration, finished)
        if finished:
            return launch.complete(resume_dir, checkpoint)
        held = launch.hold_resumed(resume_dir, checkpoint, is_writer)
    launch.warn(cfg)  # every input accepted: what runs, but probably not as meant
    with launch.holding(held):
        launch.begin(held, [held.run_dir / METRICS, held.run_dir / "tb"] if held.run_dir else [])
        if held.run_dir:
            write_inputs(held.run_dir, cfg, held.resumed)
        if not launch.started(held, f"run dir {held.run_dir}", stop):
            return Launched(launch.exit_status(None, stop), held.run_dir, None)
        summary = train(cfg, held.run_dir, resume=held.checkpoint, stop=stop, callbacks=callbacks)
    return Launched(launch.exit_status(summary, stop), held.run_dir, summary)


def write_inputs(run_dir: Path, cfg: Config, resumed: bool) -> None:
    """``config.yaml``: a new run's, or a resumed one's when its budget or W&B changed."""
    if not resumed:
        write_config(run_dir, cfg)
        return
    stored = load_config(run_dir)
    if (cfg.total_steps, cfg.wandb) != (stored.total_steps, stored.wandb):
        write_config(run_dir, cfg)  # an extended budget, or W&B turned on or off: the run's own now


def default_run_dir(cfg: Config) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{task_label(cfg.env)}-{cfg.algo}-{cfg.explore}-s{cfg.seed}-{stamp}"


def train(
    cfg: Config,
    run_dir: Path | None = None,
    progress_fn: Callable[[int, dict[str, float]], None] | None = None,
    resume: Checkpoint | None = None,
    stop: StopRequest | None = None,
    callbacks: Sequence[Callback] = (),
) -> dict[str, Any]:
    """Runs training for ``cfg``; returns the summary (also written to ``run_dir``).

    ``progress_fn(iteration, metrics)`` receives every iteration's metrics (as
    Python floats), in the manner of Brax's trainers; `callbacks` are the hooks of
    `coherent_jax.run.callbacks` (``on_start`` before the first iteration, ``on_end`` with
    the summary). With `resume` (a verified checkpoint of ``run_dir``) the run continues
    after the checkpoint's iteration. Raises `DivergenceError` when a loss or a parameter
    becomes non-finite. The summary's ``stopped_by`` names the signal when SIGINT/SIGTERM
    ended the run early, or is ``"callback"`` (with ``stop_reason``) when a callback did.
    """
    # W&B first: a server that does not answer ends the run before the slow imports and builds.
    with tracking.mirrored(_mirror_points(cfg, run_dir), init_timeout=cfg.wandb_init_timeout) as mirrors:
        from coherent_jax.agents import make_trainer  # lazy: JAX; the command starts without it
        from coherent_jax.run.loop import drive, platform, write_params  # lazy: as make_trainer

        trainer = make_trainer(cfg)
        job = Job(
            cfg=cfg,
            trainer=trainer,
            seeds=[cfg.seed],
            names=[run_dir.name if run_dir else "run"],
            run_dir=run_dir,
            point_dirs=[run_dir] if run_dir else [],
            label=f"{cfg.env} {cfg.algo} explore={cfg.explore}",
            trackers=mirrors.runs,
            callbacks=tuple(callbacks),
        )
        hooks.start(callbacks, StartInfo(cfg, run_dir, resume.iteration if resume else 0))
        out = drive(job, stop, resume, progress_fn)
        summary = run_summary(cfg, out, resume is not None, platform(out))
        if launch.report_stopped(out, run_dir):
            hooks.end(callbacks, summary)
            return summary
        write_params(trainer, out.state, [run_dir] if run_dir else [], points=False)  # every process
        if run_dir:
            atomic_write(run_dir / "summary.json", json.dumps(summary, indent=2).encode())
        mirrors.summaries = [summary]
    final = summary["final_eval_return"]
    print(
        f"{PREFIX} done: eval return {final if final is None else round(final, 1)}, "
        f"{summary['train_env_steps_per_s']:.0f} env steps/s training, compile {out.compile_s:.1f} s, "
        f"wall {summary['wall_s']:.0f} s" + (f"; run dir {run_dir}" if run_dir else ""),
        flush=True,
    )
    hooks.end(callbacks, summary)
    return summary


def run_summary(cfg: Config, out: Outcome, resumed: bool, where: dict[str, Any]) -> dict[str, Any]:
    """``summary.json``: the run's settings, final returns, timings and platform (``where``,
    `coherent_jax.run.loop.platform`)."""
    total_steps = out.done * cfg.steps_per_iteration
    last_eval = {k: v[0] for k, v in out.last_eval.items()}
    return {
        "env": cfg.env,
        "algo": cfg.algo,
        "explore": cfg.explore,
        "seed": cfg.seed,
        "env_steps": total_steps,
        "iterations": out.done,
        "final_eval_return": last_eval.get("eval/episode_return"),
        "final_eval_return_std": last_eval.get("eval/episode_return_std"),
        "final_train_return": to_float(out.last_return[0]),
        **launch.timings(out),
        "wall_s": round(out.wall_s, 2),
        "train_env_steps_per_s": round(total_steps / max(out.loop.train_s, 1e-9), 1),
        **where,
        "resumed_from": out.start if resumed else None,
        "stopped_by": out.stopped_by,
        **({"stop_reason": out.stop_reason} if out.stop_reason else {}),
        "physics": out.physics,
    }


def _mirror_points(cfg: Config, run_dir: Path | None) -> list[tuple[Path, dict[str, Any], str]]:
    """The run's W&B mirror with ``wandb=true`` and a run directory (its id lives there), else none:
    (directory, the config as ``config.yaml`` records it, name)."""
    if not (cfg.wandb and run_dir):
        return []
    return [(run_dir, stored_config(cfg), run_dir.name)]
