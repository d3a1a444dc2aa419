"""Sweeps in one program: ``python -m coherent_jax.sweep explore=coherent seeds=8 beta=[0,0.01,0.1,1]``.

Every ``key=value`` of `python -m coherent_jax.train` is accepted; a sweepable key
(declared on its config field, `config.Sweepable`; or ``seed``) given a list,
``beta=[0,0.01,0.1,1]``, becomes an axis of the grid, and ``seeds=N`` runs each
point with seeds ``seed, seed+1, ..., seed+N-1``. The grid is the product of the
axes (seeds innermost). Only the hyperparameters that live in the train state as
arrays (``state.hparams``) can vary, so the whole grid is one program:

    states = vmap(trainer.init)(init_keys, hparams)       # one row per grid point
    states, metrics = vmap(trainer.iteration)(states)     # compiled once, looped in Python

The loop over iterations is `coherent_jax.run.loop`, the same as a single run's: the
same evaluations, metrics rows, TensorBoard files, checkpoints (one for the whole
grid), ``resume=SWEEP_DIR`` (also ``total_steps=N`` to extend), SIGINT/SIGTERM
handling and divergence guard (a diverged point is named and marked, the others
continue; exit status 3 at the end). A resume may restate the grid but not change it
(`coherent_jax.sweeps.resume`); the sweep's directory is locked while it runs, as a
single run's is (`coherent_jax.run.runlock`). Each point derives its keys exactly as a
single run does (`loop.run_keys`), so point i runs the program of ``python -m
coherent_jax.train`` with that point's settings, equal to it up to float rounding:
the vmapped batch reorders float32 sums, and a chaotic task (HalfCheetah) amplifies
that difference over training until the returns part (docs/runs.md, "Sweeps").
With several JAX devices the points are split over them (`sharding.point_shardings`).

Outputs, in ``run_dir`` (default ``runs/sweep-<env>-<algo>-<explore>-<time>``): the
shared ``config.yaml`` and the grid (``grid.json``), ``versions.json``, the
checkpoint, one directory per point named by its settings holding what a single
run writes (``config.yaml``, ``metrics.jsonl``, ``tb/``, ``params.msgpack``,
``summary.json``; with ``wandb=true`` one W&B run per point, grouped by the sweep's
directory name, `coherent_jax.run.tracking`), and the aggregate over seeds of the final evaluation return per
non-seed point, ``sweep.csv`` and ``sweep.json``, also printed. A bad key or value
(an unknown key, a list for a shape setting, an empty list, a value out of range,
an axis the algorithm does not read) is one line on stderr and exit status 2
before anything is written.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from coherent_jax.config import (
    FIELDS,
    SWEEPABLE,
    Config,
    ConfigError,
    cli,
    get_value,
    help_text,
    parse_overrides,
    sweepable,
    validate,
    with_values,
)
from coherent_jax.config.parse import modern_items
from coherent_jax.config.schema import MAX_SEED
from coherent_jax.envs.registry import task_label
from coherent_jax.run import launch, multihost, rundir
from coherent_jax.run.runs import (
    METRICS,
    atomic_write,
    config_text,
    resume_point,
    split_resume,
    write_config,
)
from coherent_jax.run.stop import StopRequest
from coherent_jax.sweeps import resume as sweep_resume
from coherent_jax.sweeps.plan import Point, SweepPlan

MODULE = "coherent_jax.sweep"  # ``python -m MODULE``, which the supervisor of a distributed run starts
SUMMARY = "sweep.json"  # written last: a resumed sweep holding it (and at its budget) is complete
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
    the command-line parser shared by every entry point (`coherent_jax.config.cli`).
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
        if seeds[-1] > MAX_SEED:
            raise ConfigError(
                f"invalid value for 'seeds': {num_seeds} with seed={base.seed} (allowed: at most "
                f"{MAX_SEED - base.seed + 1}, so that seed + seeds - 1 <= {MAX_SEED}: "
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
    return Path("runs") / f"sweep-{task_label(cfg.env)}-{cfg.algo}-{cfg.explore}-{stamp}"


def sweep_help(items: Sequence[str] = ()) -> str:
    """``--help``: the sweep's options, then every training option with the value `items` (the
    other arguments) resolve it to."""
    base = parse_sweep(items).base if items else None
    return "\n".join(
        [
            "usage: python -m coherent_jax.sweep [key=value ...] [seeds=N] [KEY=[v1,v2,...] ...]",
            f"keys that take a list of values (the grid's axes): {', '.join(AXIS_KEYS)}",
            "resume=SWEEP_DIR continues a stopped sweep (total_steps=N extends a finished one)",
            "run_dir: the sweep's directory (one sub-directory per point, plus sweep.csv and sweep.json)",
            "dry_run=true (or --print-config): prints the resolved config and the grid, writes nothing",
            "",
            "sweep options:",
            *cli.help_lines(SWEEP_KEYS),
            "",
            help_text(base, items).split("\n", 1)[1],
        ]
    )


def read_sweep(argv: Sequence[str]) -> tuple[SweepPlan, Path | None]:
    """The plan of `argv` and, for ``resume=SWEEP_DIR``, the sweep's directory (its stored
    config and grid, which the items may restate but not change); raises `ConfigError`."""
    resume_dir, rest = split_resume(list(argv))
    cli.check_unique(list(argv))
    if resume_dir is None:
        return parse_sweep(argv), None
    cfg, out_dir, axes, seeds = sweep_resume.resume_plan(resume_dir, rest)
    return make_plan(cfg, axes, seeds), out_dir


def describe_sweep(argv: Sequence[str]) -> str:
    """What a dry run prints: the resolved config and the grid as YAML, and where the sweep would
    write; nothing is created or written, the devices and the memory are not checked."""
    plan, run_dir = read_sweep(argv)
    launch.warn(plan.base)
    grid = {"grid": {"axes": plan.axes, "seeds": plan.seeds, "points": len(plan.points)}}
    text = config_text(plan.base) + yaml.safe_dump(grid, sort_keys=False, default_flow_style=None)
    return (
        text.rstrip()
        + "\n"
        + launch.where(plan.base, run_dir, default_sweep_dir(plan.base), run_dir is not None)
    )


def launch_sweep(argv: Sequence[str], stop: StopRequest) -> launch.Launched:
    """Runs the command line `argv` of ``python -m coherent_jax.sweep``: parse, check, prepare
    the sweep's directory, run the grid, exit status. Raises one of `launch.BAD_INPUT`."""
    plan, resume_dir = read_sweep(argv)
    cfg = plan.base
    supervised = launch.preflight(cfg, MODULE, argv)
    if supervised is not None:
        return launch.Launched(supervised, None, None)
    from coherent_jax.sweeps.program import check_sweep, run_sweep  # lazy: JAX; bad input goes without

    is_writer = check_sweep(plan)
    if resume_dir is None:
        held = launch.hold_new(Path(cfg.run_dir) if cfg.run_dir else default_sweep_dir(cfg), is_writer)
    else:
        checkpoint = resume_point(resume_dir, cfg, resume_dir / plan.points[0].name / METRICS)
        finished = launch.is_complete(resume_dir, checkpoint, cfg, SUMMARY)
        if checkpoint is not None:
            sweep_resume.check_rows(resume_dir, [p.name for p in plan.points], checkpoint, finished)
        if finished:
            return launch.complete(resume_dir, checkpoint)
        held = launch.hold_resumed(resume_dir, checkpoint, is_writer)
    launch.warn(cfg)
    with launch.holding(held):
        if held.run_dir:
            launch.begin(held, [held.run_dir / p.name / f for p in plan.points for f in (METRICS, "tb")])
            write_grid(held.run_dir, plan, held.resumed)
        if not launch.started(held, f"sweep dir {held.run_dir}: {len(plan.points)} points", stop):
            return launch.Launched(launch.exit_status(None, stop), held.run_dir, None)
        summary = run_sweep(plan, held.run_dir, resume=held.checkpoint, stop=stop)
    return launch.Launched(launch.exit_status(summary, stop), held.run_dir, summary)


def write_grid(run_dir: Path, plan: SweepPlan, resumed: bool) -> None:
    """The shared ``config.yaml`` and, for a new sweep, ``grid.json``."""
    write_config(run_dir, dataclasses.replace(plan.base, run_dir=str(run_dir)))
    if not resumed:
        grid = {"axes": plan.axes, "seeds": plan.seeds}
        atomic_write(run_dir / GRID, json.dumps(grid, indent=2).encode())


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m coherent_jax.sweep``: help, dry run or a sweep; its exit status. Bad input is
    one line on stderr and status 2 (`launch.refuse`)."""
    try:
        mode, items = launch.split_mode(list(sys.argv[1:] if argv is None else argv))
        if mode == launch.HELP:
            return launch.answer(sweep_help(items))
        if mode == launch.DRY:
            return launch.answer(describe_sweep(items))
        with StopRequest() as stop:  # SIGINT/SIGTERM: stop after the current iteration
            return launch_sweep(items, stop).status
    except launch.REFUSED as exc:
        return launch.refuse(exc)
    except KeyboardInterrupt:  # before the stop request took over
        return launch.interrupted()


if __name__ == "__main__":
    sys.exit(multihost.run_cli(main))
