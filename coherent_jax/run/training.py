"""What a launched command runs once its input is checked: a single run (`train`) or a sweep's
grid as one vmapped program (`run_sweep`). Each builds its trainer, drives the loop
(`coherent_jax.run.loop.run_loop`), writes the parameters and the summaries; `check_train` and
`check_sweep` are their checks of the devices and the memory before anything is written.

`train` is also called directly by tests and experiments. A sweep's points share one trainer
(shapes and program); each point's hyperparameters are put into the train state at the
typed path its axis declares (`point_hparams`), so the whole grid is one program:

    states = vmap(trainer.init)(init_keys, hparams)       # one row per grid point
    states, metrics = vmap(trainer.iteration)(states)     # compiled once, looped in Python

`coherent_jax.run.launch` imports this module when a run starts: ``--help``, bad input and dry
runs go without JAX.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from flax import serialization

from coherent_jax.agents import make_trainer
from coherent_jax.agents.trainer import Trainer
from coherent_jax.config import Config, hparam_path
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.run.checkpoint import Checkpoint, stored_config, write_config
from coherent_jax.run.devices import (
    check_device_split,
    check_devices,
    point_device_count,
    resolve_num_devices,
    to_host,
)
from coherent_jax.run.loop import run_loop
from coherent_jax.run.loop_state import Job, Outcome, StopRequest, to_float
from coherent_jax.run.memory import check_memory
from coherent_jax.run.outputs import Callback, StartInfo, call_on_end, call_on_start, mirrored
from coherent_jax.run.rundir import PREFIX, atomic_write
from coherent_jax.run.sweep import Point, SweepPlan, aggregate, format_table, to_csv


def check_train(cfg: Config) -> bool:
    """The devices and the memory; returns whether this process writes the outputs."""
    is_writer = check_devices(cfg)  # several hosts: only process 0 writes
    check_memory(cfg)
    return is_writer


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
    `coherent_jax.run.outputs` (``on_start`` before the first iteration, ``on_end`` with
    the summary). With `resume` (a verified checkpoint of ``run_dir``) the run continues
    after the checkpoint's iteration. Raises `DivergenceError` when a loss or a parameter
    becomes non-finite. The summary's ``stopped_by`` names the signal when SIGINT/SIGTERM
    ended the run early, or is ``"callback"`` (with ``stop_reason``) when a callback did.
    """
    # W&B first: a server that does not answer ends the run before the trainer is built.
    with mirrored(_run_mirror_points(cfg, run_dir), init_timeout=cfg.wandb_init_timeout) as mirrors:
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
        call_on_start(callbacks, StartInfo(cfg, run_dir, resume.iteration if resume else 0))
        out = run_loop(job, stop, resume, progress_fn)
        summary = run_summary(cfg, out, resume is not None, platform(out))
        if report_stopped(out, run_dir):
            call_on_end(callbacks, summary)
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
    call_on_end(callbacks, summary)
    return summary


def run_summary(cfg: Config, out: Outcome, resumed: bool, where: dict[str, Any]) -> dict[str, Any]:
    """``summary.json``: the run's settings, final returns, timings and platform (``where``,
    `platform`)."""
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
        **timings(out),
        "wall_s": round(out.wall_s, 2),
        "train_env_steps_per_s": round(total_steps / max(out.loop.train_s, 1e-9), 1),
        **where,
        "resumed_from": out.start if resumed else None,
        "stopped_by": out.stopped_by,
        **({"stop_reason": out.stop_reason} if out.stop_reason else {}),
        "physics": out.physics,
    }


def _run_mirror_points(cfg: Config, run_dir: Path | None) -> list[tuple[Path, dict[str, Any], str]]:
    """The run's W&B mirror with ``wandb=true`` and a run directory (its id lives there), else none:
    (directory, the config as ``config.yaml`` records it, name)."""
    if not (cfg.wandb and run_dir):
        return []
    return [(run_dir, stored_config(cfg), run_dir.name)]


def timings(out: Outcome) -> dict[str, float]:
    """The seconds a summary reports: compilation, training, evaluation (this session's compile)."""
    return {
        "compile_s": round(out.compile_s, 2),
        "train_s": round(out.loop.train_s, 2),
        "eval_s": round(out.loop.eval_s, 2),
    }


def report_stopped(out: Outcome, run_dir: Path | None) -> bool:
    """Whether a signal or a callback stopped the run; if so, says where it stopped and how to
    continue."""
    if out.stopped_by is None:
        return False
    why = f" ({out.stop_reason})" if out.stop_reason else ""
    print(
        f"{PREFIX} stopped by {out.stopped_by}{why} after iteration {out.done}; "
        + (f"checkpoint saved; continue with resume={run_dir}" if run_dir else "nothing saved"),
        flush=True,
    )
    return True


def platform(out: Outcome) -> dict[str, Any]:
    """Where a summary's run ran: JAX's version, its backend, the devices used."""
    return {"jax_version": jax.__version__, "backend": jax.default_backend(), "num_devices": out.num_devices}


def write_params(trainer: Trainer, state: Any, point_dirs: list[Path], points: bool) -> None:
    """Each point's final parameters and observation statistics (flax msgpack) in its directory.

    Several processes: every process must call it (the parameters are gathered from
    all); only process 0 has directories to write to.
    """
    params = to_host(trainer.export_params(state))
    for j, d in enumerate(point_dirs):
        one = jax.tree.map(lambda x, j=j: x[j], params) if points else params
        atomic_write(d / "params.msgpack", serialization.to_bytes(one))


# --- a sweep's grid -------------------------------------------------------------------------------


def point_hparams(base_hparams: Any, point: Point) -> Any:
    """`base_hparams` (the shared trainer's ``init_hparams()``) with the point's axis values.

    Each axis key's value goes to the leaf at the typed path its `config.Sweepable`
    declares (`config.hparam_path`: the field names from the trainer's hyperparameters
    down, e.g. ``explore.beta``), as the float32 array a trainer built for the point
    would hold; no trainer is built per point.
    """
    wanted = {hparam_path(k): v for k, v in point.values.items()}
    found = set()

    def put(path, leaf):
        fields = tuple(getattr(k, "name", None) for k in path)  # GetAttrKey: a dataclass field
        if fields in wanted:
            found.add(fields)
            return jnp.asarray(wanted[fields], leaf.dtype)
        return leaf

    hparams = jax.tree_util.tree_map_with_path(put, base_hparams)
    missing = set(wanted) - found
    if missing:  # the declaration and the trainer's hyperparameters disagree
        names = sorted(".".join(p) for p in missing)
        raise RuntimeError(f"sweepable paths {names} are not in the train state's hyperparameters")
    return hparams


def stacked_hparams(plan: SweepPlan, trainer: Trainer) -> Any:
    """Every point's hyperparameters stacked on a leading axis (the vmapped init's input)."""
    base = trainer.init_hparams()
    return jax.tree.map(lambda *xs: jnp.stack(xs), *[point_hparams(base, p) for p in plan.points])


def _point_config(p: Point, d: Path) -> Config:
    """The point's own settings, as the single run that it equals would record them."""
    return dataclasses.replace(p.cfg, run_dir=str(d))


def run_sweep(
    plan: SweepPlan,
    out_dir: Path | None,
    env=None,
    eval_env=None,
    resume: Checkpoint | None = None,
    stop: StopRequest | None = None,
) -> dict[str, Any]:
    """Runs every point of ``plan`` as one vmapped program; writes and returns the aggregate.

    ``env`` and ``eval_env`` (`VecEnv`s of the plan's shapes) are built if not given.
    With `resume` (a verified checkpoint of ``out_dir``) the grid continues after it.
    """
    job = sweep_job(plan, out_dir, env, eval_env)
    group = out_dir.name if out_dir else None
    with mirrored(_sweep_mirror_points(plan, job), group, plan.base.wandb_init_timeout) as mirrors:
        out = run_loop(dataclasses.replace(job, trackers=mirrors.runs), stop, resume)
        result = sweep_result(plan, out, resume is not None)
        if report_stopped(out, out_dir):
            return result
        write_params(job.trainer, out.state, job.point_dirs, points=True)  # every process: a collective
        if out_dir is not None:
            for d, summary in zip(job.point_dirs, result["points"], strict=True):
                atomic_write(d / "summary.json", json.dumps(summary, indent=2).encode())
            atomic_write(out_dir / "sweep.csv", to_csv(plan, result["rows"]).encode())
            atomic_write(out_dir / "sweep.json", json.dumps(result, indent=2).encode())
        mirrors.summaries = result["points"]
    print(format_table(plan, result["rows"]), flush=True)
    for name, reason in result["diverged"].items():
        print(f"{PREFIX} point {name} {reason}", flush=True)
    print(
        f"{PREFIX} sweep done: {result['sweep_env_steps_per_s']:.0f} env steps/s over all points, "
        f"compile {out.compile_s:.1f} s, wall {result['wall_s']:.0f} s"
        + (f"; results in {out_dir}" if out_dir else ""),
        flush=True,
    )
    return result


def _sweep_mirror_points(plan: SweepPlan, job: Job) -> list[tuple[Path, dict[str, Any], str]]:
    """With ``wandb=true``, one W&B run per point (directory, its config as its ``config.yaml``
    holds it, its name); grouped by the caller under the sweep's directory name."""
    if not (plan.base.wandb and job.point_dirs):  # a process that writes nothing mirrors nothing
        return []
    return [
        (d, stored_config(_point_config(p, d)), p.name)
        for p, d in zip(plan.points, job.point_dirs, strict=True)
    ]


def sweep_job(plan: SweepPlan, out_dir: Path | None, env=None, eval_env=None) -> Job:
    """The loop's job for `plan`: one trainer for every point, each point's directory and config written."""
    cfg = plan.base
    env = env or VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
    eval_env = eval_env or VecEnv(
        cfg.env, cfg.eval_episodes, cfg.episode_length, cfg.physics, cfg.physics_threads
    )
    trainer = make_trainer(cfg, env, eval_env)  # shapes and program: shared by every point
    point_dirs: list[Path] = []
    if out_dir is not None:
        for p in plan.points:
            d = out_dir / p.name
            d.mkdir(exist_ok=True)  # a resumed sweep, or one started over in its own directory
            write_config(d, _point_config(p, d))
            point_dirs.append(d)
    return Job(
        cfg=cfg,
        trainer=trainer,
        seeds=[p.seed for p in plan.points],
        names=[p.name for p in plan.points],
        run_dir=out_dir,
        point_dirs=point_dirs,
        hparams=stacked_hparams(plan, trainer),
        label=f"sweep of {len(plan.points)} points ({cfg.env} {cfg.algo} explore={cfg.explore})",
    )


def point_summaries(plan: SweepPlan, out: Outcome, common: dict[str, Any]) -> list[dict[str, Any]]:
    """Each point's ``summary.json``: its settings and final returns (None for a diverged point;
    the evaluation's None too for a sweep stopped before its first evaluation)."""
    cfg = plan.base
    evals = out.last_eval.get("eval/episode_return"), out.last_eval.get("eval/episode_return_std")
    summaries = []
    for j, p in enumerate(plan.points):
        ok = j not in out.diverged
        final_eval, final_eval_std = (None if v is None or not ok else to_float(v[j]) for v in evals)
        summaries.append(
            {
                "point": p.index,
                "name": p.name,
                **{k: v for k, v in p.values.items()},
                "seed": p.seed,
                "env": cfg.env,
                "algo": cfg.algo,
                "explore": cfg.explore,
                "final_eval_return": final_eval,
                "final_eval_return_std": final_eval_std,
                "final_train_return": to_float(out.last_return[j]) if ok else None,
                "diverged": out.diverged.get(j),
                **common,
            }
        )
    return summaries


def sweep_result(plan: SweepPlan, out: Outcome, resumed: bool) -> dict[str, Any]:
    """``sweep.json``: the grid, the timings, the aggregate rows over seeds and every point's summary."""
    num_points = len(plan.points)
    total_steps = out.done * plan.base.steps_per_iteration
    common = {"env_steps": total_steps, **timings(out), **platform(out)}
    summaries = point_summaries(plan, out, common)
    return {
        "axes": plan.axes,
        "seeds": plan.seeds,
        "num_points": num_points,
        **common,
        "wall_s": round(out.wall_s, 2),
        "sweep_env_steps_per_s": round(num_points * total_steps / max(out.loop.train_s, 1e-9), 1),
        "resumed_from": out.start if resumed else None,
        "stopped_by": out.stopped_by,
        "diverged": {plan.points[j].name: reason for j, reason in sorted(out.diverged.items())},
        "rows": aggregate(plan, summaries),
        "points": summaries,
    }


def check_sweep(plan: SweepPlan) -> bool:
    """The sweep's checks before anything is written (devices, the points' split, memory);
    whether this process writes the files."""
    is_writer = check_devices(plan.base, split_envs=False)  # several hosts: only process 0 writes
    check_point_split(plan.base, plan)
    check_memory(plan.base, len(plan.points))
    return is_writer


def check_point_split(cfg: Config, plan: SweepPlan) -> None:
    """Several processes: the points must spread over every device of every process."""
    available = resolve_num_devices(cfg.num_devices, cfg.env)
    check_device_split(point_device_count(len(plan.points), available))
