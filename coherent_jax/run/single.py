"""A single run's own part of the launch path: its plan is a `Config`.

`TrainCommand` is what ``python -m coherent_jax.train`` and `coherent_jax.learn` hand to
`coherent_jax.run.launch`; `train` is its body (build the trainer, drive the loop, write the
parameters and ``summary.json``), also called directly by tests and experiments.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from coherent_jax.config import Config, parse_overrides
from coherent_jax.envs.registry import task_label
from coherent_jax.run import launch, rundir, tracking
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
    stored_config,
    write_config,
)
from coherent_jax.run.stop import StopRequest


def default_run_dir(cfg: Config) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{task_label(cfg.env)}-{cfg.algo}-{cfg.explore}-s{cfg.seed}-{stamp}"


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
        )
        out = drive(job, stop, resume, progress_fn)
        summary = run_summary(cfg, out, resume is not None, platform(out))
        if launch.report_stopped(out, run_dir):
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
        "physics": out.physics,
    }


def _mirror_points(cfg: Config, run_dir: Path | None) -> list[tuple[Path, dict[str, Any], str]]:
    """The run's W&B mirror with ``wandb=true`` and a run directory (its id lives there), else none:
    (directory, the config as ``config.yaml`` records it, name)."""
    if not (cfg.wandb and run_dir):
        return []
    return [(run_dir, stored_config(cfg), run_dir.name)]


class TrainCommand:
    """What ``python -m coherent_jax.train`` has of its own on the launch path: its plan is a `Config`."""

    module = "coherent_jax.train"
    summary_file = "summary.json"

    def config(self, plan: Config) -> Config:
        return plan

    def parse(self, argv: list[str]) -> Config:
        return parse_overrides(argv)

    def resume(self, resume_dir: str, rest: list[str]) -> tuple[Config, Path]:
        rundir.refuse_sweep_for_train(Path(resume_dir))
        return resume_config(resume_dir, rest)

    def check(self, plan: Config) -> bool:
        from coherent_jax.run.memory import check_memory  # lazy: JAX; --help and dry runs go without
        from coherent_jax.run.sharding import check_devices  # lazy: as check_memory

        is_writer = check_devices(plan)  # several hosts: only process 0 writes
        check_memory(plan)
        return is_writer

    def default_dir(self, cfg: Config) -> Path:
        return default_run_dir(cfg)

    def resume_point(self, run_dir: Path, plan: Config) -> Checkpoint | None:
        return resume_point(run_dir, plan)

    def check_rows(self, run_dir: Path, plan: Config, checkpoint: Checkpoint, finished: bool) -> None:
        rundir.check_metrics([run_dir / METRICS], checkpoint.iteration, finished)

    def outputs(self, run_dir: Path, plan: Config) -> list[Path]:
        return [run_dir / METRICS, run_dir / "tb"]

    def write_inputs(self, run_dir: Path, plan: Config, resumed: bool) -> None:
        if not resumed:
            write_config(run_dir, plan)
        else:
            stored = load_config(run_dir)
            if (plan.total_steps, plan.wandb) != (stored.total_steps, stored.wandb):
                write_config(run_dir, plan)  # an extended budget, or W&B turned on or off: the run's own now

    def dir_line(self, run_dir: Path, plan: Config) -> str:
        return f"run dir {run_dir}"

    def describe(self, plan: Config) -> str:
        return config_text(plan)

    def run(
        self, plan: Config, run_dir: Path | None, checkpoint: Checkpoint | None, stop: StopRequest
    ) -> dict:
        return train(plan, run_dir, resume=checkpoint, stop=stop)
