"""A sweep's grid run as one vmapped program (`run_sweep`): the shared trainer, each point's
hyperparameters and directory, the loop, the summaries; and the checks before it starts.
`coherent_jax.sweep` is the command; it imports this module when a sweep starts.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp

from coherent_jax.agents import make_trainer
from coherent_jax.agents.trainer import Trainer
from coherent_jax.config import Config, hparam_path
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.run import collective, launch, sharding, tracking
from coherent_jax.run.loop import drive, platform, write_params
from coherent_jax.run.loop_state import Job, Outcome, to_float
from coherent_jax.run.memory import check_memory
from coherent_jax.run.runs import PREFIX, Checkpoint, atomic_write, stored_config, write_config
from coherent_jax.run.sharding import check_devices
from coherent_jax.run.stop import StopRequest
from coherent_jax.sweeps.plan import Point, SweepPlan
from coherent_jax.sweeps.table import aggregate, format_table, to_csv


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
    with tracking.mirrored(_mirror_points(plan, job), group, plan.base.wandb_init_timeout) as mirrors:
        out = drive(dataclasses.replace(job, trackers=mirrors.runs), stop, resume)
        result = sweep_result(plan, out, resume is not None)
        if launch.report_stopped(out, out_dir):
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


def _mirror_points(plan: SweepPlan, job: Job) -> list[tuple[Path, dict[str, Any], str]]:
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
    common = {"env_steps": total_steps, **launch.timings(out), **platform(out)}
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
    available = sharding.resolve_num_devices(cfg.num_devices, cfg.env)
    collective.check_device_split(sharding.point_device_count(len(plan.points), available))
