"""Sweeps in one program: ``python -m coherent_jax.sweep explore=coherent seeds=8 beta=[0,0.01,0.1,1]``.

Every ``key=value`` of `python -m coherent_jax.train` is accepted; a sweepable key
(declared on its config field, `config.Sweepable`; or ``seed``) given a list,
``beta=[0,0.01,0.1,1]``, becomes an axis of the grid, and ``seeds=N`` runs each
point with seeds ``seed, seed+1, ..., seed+N-1``. The grid is the product of the
axes (seeds innermost). Only the hyperparameters that live in the train state as
arrays (``state.hparams``) can vary, so the whole grid is one program:

    states = vmap(trainer.init)(init_keys, hparams)       # one row per grid point
    states, metrics = vmap(trainer.iteration)(states)     # compiled once, looped in Python

The loop over iterations is `coherent_jax.loop`, the same as a single run's: the
same evaluations, metrics rows, TensorBoard files, checkpoints (one for the whole
grid), ``resume=SWEEP_DIR`` (also ``total_steps=N`` to extend), SIGINT/SIGTERM
handling and divergence guard (a diverged point is named and marked, the others
continue; exit status 3 at the end). A resume may restate the grid but not change it
(`coherent_jax.sweep_resume`); the sweep's directory is locked while it runs, as a
single run's is (`coherent_jax.runlock`). Each point derives its keys exactly as a
single run does (`loop.run_keys`), so point i equals ``python -m
coherent_jax.train`` with that point's settings. With several JAX devices the
points are split over them (`parallel.point_shardings`).

Outputs, in ``run_dir`` (default ``runs/sweep-<env>-<algo>-<explore>-<time>``): the
shared ``config.yaml`` and the grid (``grid.json``), ``versions.json``, the
checkpoint, one directory per point named by its settings holding what a single
run writes (``config.yaml``, ``metrics.jsonl``, ``tb/``, ``params.msgpack``,
``summary.json``), and the aggregate over seeds of the final evaluation return per
non-seed point, ``sweep.csv`` and ``sweep.json``, also printed. A bad key or value
(an unknown key, a list for a shape setting, an empty list, a value out of range,
an axis the algorithm does not read) is one line on stderr and exit status 2
before anything is written.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coherent_jax import cli, distributed, limits, rundir
from coherent_jax.config import (
    FIELDS,
    SWEEPABLE,
    Config,
    ConfigError,
    get_value,
    help_text,
    hparam_name,
    modern_items,
    parse_overrides,
    sweepable,
    validate,
    with_values,
)
from coherent_jax.loop import (
    PREFIX,
    Job,
    StopRequest,
    quiet_imports,
    run_command,
    run_loop,
    to_float,
    write_params,
)
from coherent_jax.memory import check_memory
from coherent_jax.runs import (
    METRICS,
    Checkpoint,
    CheckpointError,
    atomic_write,
    prepare_output_dir,
    record_versions,
    resume_point,
    split_resume,
    write_config,
)
from coherent_jax.sweep_table import aggregate, fmt, format_table, to_csv

# Keys that may take a list of values: the state's array hyperparameters, and seed.
AXIS_KEYS = (*SWEEPABLE, "seed")
GRID = rundir.GRID
# The sweep's own keys (everything else is a training-config key or an axis).
SWEEP_KEYS = {
    "seeds": cli.Key(
        default=None,
        parse=cli.int_at_least(1),
        allowed="an integer >= 1",
        help="runs every point with seeds seed, seed+1, ..., seed+N-1 (default: seed alone)",
    ),
}
EXIT_DIVERGED = 3


@dataclasses.dataclass(frozen=True)
class Point:
    """One grid point: its settings along the non-seed axes, its seed and its config."""

    index: int
    values: dict[str, Any]
    seed: int
    cfg: Config

    @property
    def name(self) -> str:
        # A group's key by its last part (``beta=0.1``): the names sweeps have always had.
        parts = [f"{k.rsplit('.', 1)[-1]}={fmt(v)}" for k, v in self.values.items()]
        return "-".join([f"p{self.index:03d}", *parts, f"seed={self.seed}"])


@dataclasses.dataclass(frozen=True)
class SweepPlan:
    """The validated grid: the shared config, the axes in the order given, the seeds, the points."""

    base: Config
    axes: dict[str, list[Any]]
    seeds: list[int]
    points: list[Point]


def _is_list(text: str) -> bool:
    return text.startswith("[") and text.endswith("]")


def _list_items(key: str, text: str) -> list[str]:
    items = [s.strip() for s in text[1:-1].split(",")]
    if items == [""] or any(not s for s in items):
        raise ConfigError(
            f"invalid value for {key!r}: {text!r} (allowed: a non-empty list of values, e.g. [0.01,0.1])"
        )
    return items


def parse_sweep(argv: Sequence[str]) -> SweepPlan:
    """Splits ``key=value`` strings into the grid; raises `ConfigError` naming the bad key or value.

    The axes (a sweepable key or ``seed`` given a list) are taken out first; the rest,
    the sweep's own keys (`SWEEP_KEYS`) and single training-config values, go through
    the command-line parser shared by every entry point (`coherent_jax.cli`).
    """
    fields = FIELDS
    scalars: list[str] = []
    axes: dict[str, list[str]] = {}
    for item in modern_items(argv):
        key, text = cli.split_item(item)
        list_field = key in fields and "list" in str(fields[key].type)
        # policy_hidden=[64,64] is one value of a list setting; [[8],[16]] would be an axis of them.
        if key in fields and _is_list(text) and (not list_field or text.startswith("[[")):
            if key not in AXIS_KEYS:
                raise ConfigError(
                    f"invalid value for {key!r}: {text!r} (allowed: one value; it sets shapes or the "
                    f"program, so it cannot vary within a sweep; keys that take a list: "
                    f"{', '.join(AXIS_KEYS)})"
                )
            axes[key] = _list_items(key, text)
        else:
            scalars.append(item)
    parsed = cli.parse_command(scalars, SWEEP_KEYS, command="sweep")
    base, num_seeds, scalars = parsed.config, parsed.settings["seeds"], parsed.config_items
    seed_items = axes.pop("seed", None)
    if seed_items is not None and num_seeds is not None:
        raise ConfigError(
            f"invalid key 'seeds': {num_seeds} with seed={seed_items} "
            "(allowed: either seeds=N or a list of seeds)"
        )
    for key in axes:
        if not sweepable(key).read_by(base.algo, base.explore):
            raise ConfigError(
                f"invalid key {key!r}: algo={base.algo} explore={base.explore} does not use it "
                f"(allowed: keys that change its hyperparameters)"
            )
    # Each value parsed as a single override would be (typed, and checked: e.g. beta=2).
    typed = {
        k: [get_value(parse_overrides([*scalars, f"{k}={v}"]), k) for v in items] for k, items in axes.items()
    }
    if seed_items is None:
        seeds = [base.seed + i for i in range(num_seeds or 1)]
        if seeds[-1] > limits.MAX_SEED:
            raise ConfigError(
                f"invalid value for 'seeds': {num_seeds} with seed={base.seed} (allowed: at most "
                f"{limits.MAX_SEED - base.seed + 1}, so that seed + seeds - 1 <= {limits.MAX_SEED}: "
                "the PRNG key is derived from the seed's 32 bits)"
            )
    else:
        seeds = [parse_overrides([*scalars, f"seed={v}"]).seed for v in seed_items]
    return make_plan(base, typed, seeds)


def make_plan(base: Config, axes: dict[str, list[Any]], seeds: list[int]) -> SweepPlan:
    """The grid of `axes` x `seeds` over `base` (seeds innermost), each point's config validated."""
    points: list[Point] = []
    for combo in itertools.product(*axes.values(), seeds):
        *values, seed = combo
        settings = dict(zip(axes, values, strict=True))
        cfg = validate(with_values(base, {**settings, "seed": seed}))
        points.append(Point(index=len(points), values=settings, seed=seed, cfg=cfg))
    return SweepPlan(base=base, axes={k: list(v) for k, v in axes.items()}, seeds=list(seeds), points=points)


def default_sweep_dir(cfg: Config) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"sweep-{cfg.env}-{cfg.algo}-{cfg.explore}-{stamp}"


def point_hparams(base_hparams: Any, point: Point) -> Any:
    """`base_hparams` (the shared trainer's ``init_hparams()``) with the point's axis values.

    Each axis key's value goes to the leaf its `config.Sweepable` names (the key's own
    name unless declared otherwise), as the float32 array a trainer built for the
    point would hold; no trainer is built per point.
    """
    import jax
    import jax.numpy as jnp

    wanted = {hparam_name(k): v for k, v in point.values.items()}
    found = set()

    def put(path, leaf):
        last = path[-1]
        name = getattr(last, "name", getattr(last, "key", None))
        if name in wanted:
            found.add(name)
            return jnp.asarray(wanted[name], leaf.dtype)
        return leaf

    hparams = jax.tree_util.tree_map_with_path(put, base_hparams)
    missing = set(wanted) - found
    if missing:  # the declaration and the trainer's hyperparameters disagree
        raise RuntimeError(f"sweepable keys {sorted(missing)} are not in the train state's hyperparameters")
    return hparams


def stacked_hparams(plan: SweepPlan, trainer: Any) -> Any:
    """Every point's hyperparameters stacked on a leading axis (the vmapped init's input)."""
    import jax
    import jax.numpy as jnp

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
    import contextlib

    import jax

    from coherent_jax.agents import make_trainer
    from coherent_jax.envs.vec_env import VecEnv

    cfg = plan.base
    env = env or VecEnv(cfg.env, cfg.num_envs, cfg.episode_length, cfg.physics, cfg.physics_threads)
    eval_env = eval_env or VecEnv(
        cfg.env, cfg.eval_episodes, cfg.episode_length, cfg.physics, cfg.physics_threads
    )
    trainer = make_trainer(cfg, env, eval_env)  # shapes and program: shared by every point
    num_points = len(plan.points)
    point_dirs: list[Path] = []
    if out_dir is not None:
        for p in plan.points:
            d = out_dir / p.name
            d.mkdir(exist_ok=True)  # a resumed sweep, or one started over in its own directory
            write_config(d, _point_config(p, d))
            point_dirs.append(d)
    job = Job(
        cfg=cfg,
        trainer=trainer,
        seeds=[p.seed for p in plan.points],
        names=[p.name for p in plan.points],
        run_dir=out_dir,
        point_dirs=point_dirs,
        hparams=stacked_hparams(plan, trainer),
        label=f"sweep of {num_points} points ({cfg.env} {cfg.algo} explore={cfg.explore})",
    )
    with contextlib.ExitStack() as stack:
        stop = stop or stack.enter_context(StopRequest())
        out = run_loop(job, stop, resume)

    total_steps = out.done * cfg.steps_per_iteration
    common = {
        "env_steps": total_steps,
        "compile_s": round(out.compile_s, 2),
        "train_s": round(out.loop.train_s, 2),
        "eval_s": round(out.loop.eval_s, 2),
        "jax_version": jax.__version__,
        "backend": jax.default_backend(),
        "num_devices": out.num_devices,
    }
    nan = [float("nan")] * num_points
    evals, stds = (out.last_eval.get(f"eval/episode_return{s}", nan) for s in ("", "_std"))
    summaries = []
    for j, p in enumerate(plan.points):
        ok = j not in out.diverged
        summaries.append(
            {
                "point": p.index,
                "name": p.name,
                **{k: v for k, v in p.values.items()},
                "seed": p.seed,
                "env": cfg.env,
                "algo": cfg.algo,
                "explore": cfg.explore,
                "final_eval_return": to_float(out.last_eval["eval/episode_return"][j]) if ok else None,
                "final_eval_return_std": to_float(out.last_eval["eval/episode_return_std"][j])
                if ok
                else None,
                "final_train_return": to_float(out.last_return[j]) if ok else None,
                "diverged": out.diverged.get(j),
                **common,
            }
        )
    rows = aggregate(plan, summaries)
    result = {
        "axes": plan.axes,
        "seeds": plan.seeds,
        "num_points": num_points,
        **common,
        "wall_s": round(out.wall_s, 2),
        "sweep_env_steps_per_s": round(num_points * total_steps / max(out.loop.train_s, 1e-9), 1),
        "resumed_from": out.start if resume is not None else None,
        "stopped_by": out.stopped_by,
        "diverged": {plan.points[j].name: reason for j, reason in sorted(out.diverged.items())},
        "rows": rows,
        "points": summaries,
    }
    if out.stopped_by is not None:
        print(
            f"{PREFIX} stopped by {out.stopped_by} after iteration {out.done}; "
            + (f"checkpoint saved; continue with resume={out_dir}" if out_dir else "nothing saved"),
            flush=True,
        )
        return result
    write_params(trainer, out.state, point_dirs, points=True)  # every process: a collective
    if out_dir is not None:
        for d, summary in zip(point_dirs, summaries, strict=True):
            atomic_write(d / "summary.json", json.dumps(summary, indent=2).encode())
        atomic_write(out_dir / "sweep.csv", to_csv(plan, rows).encode())
        atomic_write(out_dir / "sweep.json", json.dumps(result, indent=2).encode())
    print(format_table(plan, rows), flush=True)
    for name, reason in result["diverged"].items():
        print(f"{PREFIX} point {name} {reason}", flush=True)
    print(
        f"{PREFIX} sweep done: {result['sweep_env_steps_per_s']:.0f} env steps/s over all points, "
        f"compile {out.compile_s:.1f} s, wall {result['wall_s']:.0f} s"
        + (f"; results in {out_dir}" if out_dir else ""),
        flush=True,
    )
    return result


def sweep_help() -> str:
    return "\n".join(
        [
            "usage: python -m coherent_jax.sweep [key=value ...] [seeds=N] [KEY=[v1,v2,...] ...]",
            f"keys that take a list of values (the grid's axes): {', '.join(AXIS_KEYS)}",
            "resume=SWEEP_DIR continues a stopped sweep (total_steps=N extends a finished one)",
            "run_dir: the sweep's directory (one sub-directory per point, plus sweep.csv and sweep.json)",
            "",
            "sweep options:",
            *cli.help_lines(SWEEP_KEYS),
            "",
            help_text().split("\n", 1)[1],
        ]
    )


def main(argv: Sequence[str] | None = None) -> int:
    return run_command(list(sys.argv[1:] if argv is None else argv), sweep_help, _main)


def _main(argv: list[str], stop: StopRequest) -> int:
    from coherent_jax import runlock, sweep_resume
    from coherent_jax.parallel import check_devices

    resume_dir, rest = split_resume(argv)
    checkpoint, lock = None, None
    try:
        cli.check_unique(argv)
        if resume_dir is not None:
            cfg, out_dir, axes, seeds = sweep_resume.resume_plan(resume_dir, rest)
            plan = make_plan(cfg, axes, seeds)
            if distributed.needs_supervisor(cfg.distributed):
                return distributed.supervise("coherent_jax.sweep", argv)
            # Several hosts: every process reads the checkpoint, only process 0 writes.
            is_writer = check_devices(cfg, split_envs=False)
            check_point_split(cfg, plan)
            check_memory(cfg, len(plan.points))
            checkpoint = resume_point(out_dir, cfg, out_dir / plan.points[0].name / METRICS)
            if checkpoint is not None:
                done = checkpoint.iteration >= cfg.num_iterations and (out_dir / "sweep.json").exists()
                sweep_resume.check_rows(out_dir, [p.name for p in plan.points], checkpoint, done)
                if done:
                    print(f"{PREFIX} {out_dir} is already complete ({checkpoint.iteration} iterations)")
                    return 0
            out_dir = out_dir if is_writer else None
            lock = runlock.acquire(out_dir, "resume") if out_dir else None
        else:
            plan = parse_sweep(argv)
            cfg = plan.base
            if distributed.needs_supervisor(cfg.distributed):
                return distributed.supervise("coherent_jax.sweep", argv)
            writer = check_devices(cfg, split_envs=False)
            check_point_split(cfg, plan)
            check_memory(cfg, len(plan.points))
            out_dir = None
            if writer:
                path = Path(cfg.run_dir) if cfg.run_dir else default_sweep_dir(cfg)
                runlock.refuse_if_held(path, "run_dir")
                out_dir = prepare_output_dir(path)
                lock = runlock.acquire(out_dir, "run_dir")
    except (ConfigError, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    with lock or contextlib.nullcontext():
        return _run(cfg, plan, out_dir, resume_dir, checkpoint, stop)


def _run(cfg: Config, plan: SweepPlan, out_dir: Path | None, resume_dir, checkpoint, stop) -> int:
    """Writes the sweep's config, grid and versions, runs it, and returns the exit status."""
    if out_dir is not None:
        cfg = dataclasses.replace(cfg, run_dir=str(out_dir))
        write_config(out_dir, cfg)
        if resume_dir is None:
            grid = {"axes": plan.axes, "seeds": plan.seeds}
            atomic_write(out_dir / GRID, json.dumps(grid, indent=2).encode())
        record_versions(out_dir, None if resume_dir is None else (checkpoint.iteration if checkpoint else 0))
        print(f"{PREFIX} sweep dir {out_dir}: {len(plan.points)} points", flush=True)
    if stop.signum is not None:
        print(f"{PREFIX} stopped by {stop.name} before training started", flush=True)
        return 128 + stop.signum
    quiet_imports()
    try:
        result = run_sweep(plan, out_dir, resume=checkpoint, stop=stop)
    except CheckpointError as exc:  # a state that does not fit this grid, found on restoring it
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 2
    if result["stopped_by"] is not None:
        return 128 + int(signal.Signals[result["stopped_by"]])
    return EXIT_DIVERGED if result["diverged"] else 0


def check_point_split(cfg: Config, plan: SweepPlan) -> None:
    """Several processes: the points must spread over every device of every process."""
    from coherent_jax import parallel

    available = parallel.resolve_num_devices(cfg.num_devices)
    distributed.check_device_split(parallel.point_device_count(len(plan.points), available))


if __name__ == "__main__":
    sys.exit(distributed.run_cli(main))
