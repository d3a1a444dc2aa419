"""``python -m coherent_jax.study``: a study from its file or command line to its verdict.

    python -m coherent_jax.study STUDY.yaml                       # run it (or continue it)
    python -m coherent_jax.study env=[gym:Pusher-v5,hopper] explore=[action,coherent,pink] \\
        algo=ppo seeds=10 total_steps=500000 out=studies/pusher
    python -m coherent_jax.study STUDY.yaml executor=ray ray.address=HEAD:6379  # on a Ray cluster
    python -m coherent_jax.study STUDY.yaml plan=true             # its cost, before it runs
    python -m coherent_jax.study STUDY.yaml status=true           # each cell's state
    python -m coherent_jax.study report DIR                       # REPORT.md and its figures
    python -m coherent_jax.study curves DIR                       # its curves table, from the logs

The study's keys (`coherent_jax.study.spec`): ``name``, ``out``, ``seeds``, ``total_steps``,
``env`` (its tasks), ``algo``, ``explore`` (its strategies), ``compare``, ``metrics``; with
a file, they override the file's. Every other ``key=value`` is a training setting of every
cell. The command's own keys are `KEYS` (``--plan``, ``--status`` and the like are their
flags). Bad input (a bad key or value in any cell, an unknown strategy, a refused (algo,
explore) pair, a folder holding another study) is one line on stderr and exit status 2
before anything runs or is written. Exit status 0 when every cell is done (``verify``:
bit-identical, or not comparable: made on another CPU), 1 when a cell's sweep failed
(``verify``: a cell differs). A study with a ``tune:`` block tunes its strategies first
(`coherent_jax.study.tune_run`); ``plan`` and ``status`` show both stages.
"""

from __future__ import annotations

import fnmatch
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coherent_jax.config import ConfigError, cli
from coherent_jax.exit_codes import EXIT_BAD_INPUT
from coherent_jax.study import carry, cost, curves, execute, plan, ray_executor, spec, tune_run, verify
from coherent_jax.study.cell import Cell, StudyError

EXECUTORS = ("local", "ray")  # this machine's worker processes; a Ray cluster's tasks (ray_executor)
KEYS: dict[str, cli.Key] = {
    "workers": cli.Key(
        0,
        cli.int_at_least(0),
        "an integer >= 0",
        "cells at a time (0: as many as fit cores and memory; with ray, the cluster's CPUs)",
    ),
    "executor": cli.Key(
        "local",
        cli.choice(EXECUTORS),
        ", ".join(EXECUTORS),
        "what runs the cells: worker processes here, or Ray tasks on a cluster",
    ),
    "ray.address": cli.Key(
        "auto", ray_executor.parse_address, ray_executor.ADDRESSES, "executor=ray: the Ray cluster's address"
    ),
    "ray.cpus_per_cell": cli.Key(
        1.0, cli.positive_float, "a number > 0", "executor=ray: the CPUs each cell's Ray task reserves"
    ),
    "plan": cli.Key(
        False, cli.boolean, "true or false", "list the cells and programs, probe each program, estimate"
    ),
    "probe": cli.Key(
        plan.PROBE_ITERATIONS, cli.int_at_least(1), "an integer >= 1", "iterations of a plan's probe"
    ),
    "status": cli.Key(
        False, cli.boolean, "true or false", "print each cell's state and the compute it needs"
    ),
    "cells": cli.Key(
        [], lambda t: spec._names(t, "cells"), "a glob or a list of globs", "only the cells named"
    ),
    "verify": cli.Key(False, cli.boolean, "true or false", "re-run finished cells' first iterations at HEAD"),
    "iterations": cli.Key(
        verify.DEFAULT_ITERATIONS, cli.int_at_least(1), "an integer >= 1", "verify's iterations"
    ),
    "pack": cli.Key(False, cli.boolean, "true or false", "write each stopped cell's carry file"),
    "commit": cli.Key(False, cli.boolean, "true or false", "git-commit each finished cell's kept files"),
}
STUDY_KEYS = {"name": "name", "out": "out", "seeds": "seeds", "total_steps": "total_steps", "env": "tasks",
              "tasks": "tasks", "algo": "algos", "algos": "algos", "explore": "strategies",
              "strategies": "strategies", "compare": "compare", "metrics": "metrics"}  # fmt: skip
FLAGS = ("--plan", "--status", "--verify", "--pack", "--commit")


def _value(key: str, text: str) -> Any:
    """A study key's value from the command line (names stay text: ``gym:Pusher-v5``)."""
    if key in ("tasks", "algos", "strategies", "compare", "metrics", "name", "out"):
        return text
    return spec.yaml.safe_load(text)


def parse(argv: Sequence[str]) -> tuple[spec.Study, dict[str, Any], str]:
    """The study, the command's settings and the study file (or "") of `argv`; `StudyError` or
    `ConfigError` in one line for bad input."""
    file, items = "", []
    for arg in argv:
        if arg in FLAGS:
            items.append(f"{arg[2:]}=true")
        elif "=" in arg:
            items.append(arg)
        elif not file:
            file = arg
        else:
            raise StudyError(f"invalid argument {arg!r} (allowed: one study file, then key=value items)")
    cli.check_unique(items)
    data = spec.read_file(Path(file)) if file else {}
    settings = {k: key.default for k, key in KEYS.items()}
    extra = []
    for item in items:
        key, text = cli.split_item(item)
        if key in KEYS:
            settings[key] = cli.parse_value(key, text, KEYS[key])
        elif key in STUDY_KEYS:
            data[STUDY_KEYS[key]] = (
                str(Path(text).absolute()) if key == "out" else _value(STUDY_KEYS[key], text)
            )
        else:
            extra.append(item)
    if extra:
        data["settings"] = [*spec._items(data.get("settings"), "settings"), *extra]
        for block in data.get("grids") or []:
            if isinstance(block, dict) and "settings" in block:
                block["settings"] = [*spec._items(block["settings"], "settings"), *extra]
    base = Path(file).absolute().parent if file else Path.cwd()
    default = Path(file).stem if file else Path(str(data.get("out") or "study")).name
    return spec.make_study(data, base, default), settings, file


def select(cells: list[Cell], patterns: Sequence[str], name: str) -> list[Cell]:
    """The cells whose name matches one of `patterns` (all without any); an unmatched pattern is refused."""
    if not patterns:
        return cells
    unmatched = [p for p in patterns if not any(fnmatch.fnmatchcase(c.name, p) for c in cells)]
    if unmatched:
        raise StudyError(
            f"unknown cell {unmatched[0]!r} in study {name!r} (allowed: {', '.join(c.name for c in cells)})"
        )
    return [c for c in cells if any(fnmatch.fnmatchcase(c.name, p) for p in patterns)]


def record(study: spec.Study, cells: Sequence[Cell], argv: Sequence[str]) -> dict[str, Any]:
    """``study.json``: what the report reads of the study."""
    return {
        "name": study.name,
        "base": str(study.base),
        "command": " ".join(["python -m coherent_jax.study", *argv]),
        "labels": study.labels(),
        "metrics": list(study.metrics),
        "compare": [str(c) for c in study.comparisons],
        "cells": [c.spec() for c in cells],
        "tune": tune_run.record(study),
    }


def make_executor(settings: dict[str, Any]) -> tuple[execute.Executor, str]:
    """The executor the settings ask for, and how the start line names it. ``executor=ray``
    connects to its cluster here: no Ray, or no cluster at ``ray.address``, is a `StudyError`."""
    if settings["executor"] == "ray":
        address, cpus = settings["ray.address"], settings["ray.cpus_per_cell"]
        executor = ray_executor.RayExecutor(address, cpus, settings["workers"])
        return (
            executor,
            f"executor=ray at {address}, {executor.slots} cells at a time, ray.cpus_per_cell={cpus:g}",
        )
    workers = settings["workers"] or execute.default_workers()
    return execute.LocalExecutor(workers), f"workers={workers}"


def run(study: spec.Study, cells: list[Cell], settings: dict[str, Any], argv: Sequence[str]) -> int:
    """Runs every cell not done to the end; the exit status."""
    executor, how = make_executor(settings)
    try:
        with execute.holding(study.out):
            if study.tune is not None:  # the tuning first, then the cells at the values it chose
                execute.write_record(study.out, record(study, study.cells(), argv))
                study, failed = tune_run.run_stage(study, executor)
                if failed:
                    print(f"[study] tuning failed: {', '.join(failed)} (see their run.log)", file=sys.stderr)
                    return 1
                cells = tune_run.selected(study, cells)
                execute.check_folder(study.out, study.name, cells)
            execute.write_record(study.out, record(study, study.cells(), argv))
            print(f"[study] {study.name}: {len(cells)} cells in {study.out}, {how}", flush=True)
            on_done = (lambda c: execute.commit_cell(c, study.out)) if settings["commit"] else None
            probed = plan.cached_rates(cells, study.base)  # a plan's probes, if one was made here
            failed = execute.run_cells(cells, study.out, study.base, executor, on_done=on_done, probed=probed)
    finally:
        if isinstance(executor, ray_executor.RayExecutor):
            executor.close()
    print(cost.status(cells, study.out))
    if failed:
        print(f"[study] failed: {', '.join(failed)} (see their run.log)", file=sys.stderr)
        return 1
    return 0


def dispatch(study: spec.Study, cells: list[Cell], settings: dict[str, Any], argv: Sequence[str]) -> int:
    """The mode the settings choose: status, plan, verify, pack, or a run."""
    if settings["status"]:
        if study.tune is not None:
            print(tune_run.status_text(study))
        print(cost.status(cells, study.out))
        return 0
    if settings["plan"]:
        workers = settings["workers"] or execute.default_workers()
        try:
            cells = [*tune_run.plan_cells(study), *cells]
            progs, of = plan.measure(cells, study.base, settings["probe"])
        except RuntimeError as exc:  # a probe's sweep failed: no estimate
            print(f"error: {exc}", file=sys.stderr)
            return 1
        print(f"study {study.name} ({study.out}):")
        print(plan.plan_text(cells, study.out, progs, of, workers))
        return 0
    if settings["verify"]:
        file = " ".join(a for a in argv if "=" not in a and not a.startswith("--"))
        command = f"python -m coherent_jax.study {file} verify=true cells={{cell}}"
        return verify.run(cells, study.out, settings["iterations"], cwd=study.base, command=command)
    if settings["pack"]:
        return execute.pack_cells(cells, study.out, settings["commit"])
    return run(study, cells, settings, argv)


def rebuild_tables(folders: Sequence[str]) -> int:
    """``curves DIR...``: each study's curves table rebuilt from the local logs of its finished cells."""
    bad = [
        f for f in folders if not (Path(f) / execute.RECORD).is_file() and not Path(f, curves.TABLE).is_file()
    ]
    if not folders or bad:
        print(
            f"error: invalid study folder {(bad or [''])[0]!r} (allowed: curves DIR..., a study's folders)",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT
    for folder in folders:
        path = curves.build(Path(folder))
        print(f"{path}: {len(curves.finished_cells(Path(folder)))} finished cells")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "help") for a in argv) or not argv:
        print(__doc__)
        print("options (key=default):", *cli.help_lines(KEYS), sep="\n")
        return 0
    if argv[0] == "report":
        from coherent_jax.study import report  # lazy: matplotlib and rliable, only for the report

        return report.main(argv[1:])
    if argv[0] == "curves":
        return rebuild_tables(argv[1:])
    try:
        study, settings, _ = parse(argv)
        study = tune_run.resolve(study)  # at the values its tuning chose, once it is done
        cells = select(study.cells(), settings["cells"], study.name)
        spec.check(study, cells)
        if not settings["status"] and not settings["verify"]:
            execute.check_folder(study.out, study.name, study.cells())
            tune_run.check_folder(study)
        return dispatch(study, cells, settings, argv)
    except (StudyError, ConfigError, carry.CarryError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return 130
