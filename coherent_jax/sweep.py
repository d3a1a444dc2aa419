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
(`coherent_jax.run.sweep`); the sweep's directory is locked while it runs, as a
single run's is (`coherent_jax.run.rundir`). Each point derives its keys exactly as a
single run does (`loop.run_keys`), so point i runs the program of ``python -m
coherent_jax.train`` with that point's settings, equal to it up to float rounding:
the vmapped batch reorders float32 sums, and a chaotic task (HalfCheetah) amplifies
that difference over training until the returns part (docs/runs.md, "Sweeps").
With several JAX devices the points are split over them (`devices.point_shardings`).

Outputs, in ``run_dir`` (default ``runs/sweep-<env>-<algo>-<explore>-<time>``): the
shared ``config.yaml`` and the grid (``grid.json``), ``versions.json``, the
checkpoint, one directory per point named by its settings holding what a single
run writes (``config.yaml``, ``metrics.jsonl``, ``tb/``, ``params.msgpack``,
``summary.json``; with ``wandb=true`` one W&B run per point, grouped by the sweep's
directory name, `coherent_jax.run.outputs`), and the aggregate over seeds of the final evaluation return per
non-seed point, ``sweep.csv`` and ``sweep.json``, also printed. A bad key or value
(an unknown key, a list for a shape setting, an empty list, a value out of range,
an axis the algorithm does not read) is one line on stderr and exit status 2
before anything is written.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from coherent_jax.config import cli, help_text
from coherent_jax.run import launch, multihost
from coherent_jax.run.launch import describe_sweep, launch_sweep
from coherent_jax.run.loop_state import StopRequest
from coherent_jax.run.sweep import AXIS_KEYS, SWEEP_KEYS, parse_sweep


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


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m coherent_jax.sweep``: help, dry run or a sweep; its exit status. Bad input is
    one line on stderr and status 2 (`launch.refuse`)."""
    try:
        mode, items = launch.split_mode(list(sys.argv[1:] if argv is None else argv))
        if mode == launch.HELP:
            return launch.print_answer(sweep_help(items))
        if mode == launch.DRY:
            return launch.print_answer(describe_sweep(items))
        with StopRequest() as stop:  # SIGINT/SIGTERM: stop after the current iteration
            return launch_sweep(items, stop).status
    except launch.REFUSED as exc:
        return launch.refuse(exc)
    except KeyboardInterrupt:  # before the stop request took over
        return launch.interrupted()


if __name__ == "__main__":
    sys.exit(multihost.run_cli(main))
