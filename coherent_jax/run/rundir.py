"""What kind of directory a command was given, and whether its logged rows are whole.

* A sweep's root holds ``grid.json`` beside its shared ``config.yaml``; each point is a
  sub-directory with a single run's ``config.yaml`` and rows but no checkpoint (the
  sweep keeps one for the whole grid). `refuse_sweep_for_train` and `sweep_points`
  let ``train`` and ``evaluate`` say which command or directory to use instead of
  failing later on a shape mismatch.
* `metrics_problem` compares a ``metrics.jsonl`` with the checkpoint's iteration: a
  file truncated or damaged (a line that is not a metrics row) would otherwise be
  reported as complete, or have its lost rows silently skipped by a resume.
* `set_aside` keeps the rows of a resume that found no checkpoint (it starts over) as
  ``metrics.jsonl.discarded-N``; `first_missing` and `discard_new_dir` remove a new run's
  directory again when its start fails (W&B not starting).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from coherent_jax.config import ConfigError

GRID = "grid.json"  # a sweep's grid, in its root directory
CONFIG = "config.yaml"


def is_sweep(directory: Path) -> bool:
    """Whether `directory` is a sweep's root (it holds ``grid.json``)."""
    return (Path(directory) / GRID).is_file()


def sweep_points(directory: Path) -> list[Path]:
    """A sweep root's point directories (those holding a ``config.yaml``), sorted."""
    return sorted(p for p in Path(directory).iterdir() if p.is_dir() and (p / CONFIG).is_file())


def check_one_run(run_dir: Path, verb: str) -> None:
    """Refuses, in one line, a `run_dir` that is not a directory or is a sweep (naming its
    points, one of which the command can `verb`)."""
    if not run_dir.is_dir():
        raise ConfigError(
            f"invalid run directory {str(run_dir)!r}: not a directory (allowed: a run directory)"
        )
    if is_sweep(run_dir):
        points = ", ".join(str(p) for p in sweep_points(run_dir)) or "none yet"
        raise ConfigError(
            f"invalid run directory {str(run_dir)!r}: this is a sweep; {verb} one of its points: {points}"
        )


def refuse_sweep_for_train(directory: Path) -> None:
    """Raises `ConfigError` when ``train resume=`` is given a sweep's root or one of its points."""
    directory = Path(directory)
    if is_sweep(directory):
        raise ConfigError(
            f"{str(directory)} is a sweep; resume it with python -m coherent_jax.sweep resume={directory}"
        )
    parent = directory.absolute().parent
    if is_sweep(parent) and (directory / CONFIG).is_file():
        root = directory.parent
        raise ConfigError(
            f"{str(directory)} is a point of the sweep {str(root)}; resume the sweep with "
            f"python -m coherent_jax.sweep resume={root}"
        )


def metrics_problem(path: Path, iteration: int, finished: bool) -> str | None:
    """What is wrong with the rows of `path` for a checkpoint at `iteration`, or None.

    Rows 1..``iteration`` must be there, readable and in order. A run killed while
    writing leaves a partial line past them, which a resume drops; a finished run
    (`finished`) has exactly its ``iteration`` rows and nothing else.
    """
    path = Path(path)
    if iteration == 0:
        return None
    if not path.is_file():
        return f"{path.name} is missing; the checkpoint is at iteration {iteration}"
    lines = path.read_text(errors="replace").splitlines()
    for number, line in enumerate(lines, start=1):
        try:
            row = json.loads(line)
            at = row["iteration"] if isinstance(row, dict) else None
        except (json.JSONDecodeError, KeyError):
            at = None
        if at != number:
            if number > iteration and not finished:
                return None  # past the checkpoint: recomputed on resume
            what = "not a metrics row" if at is None else f"the row of iteration {at}"
            return (
                f"{path.name} is damaged: line {number} is {what}, after {number - 1} good rows; "
                f"the checkpoint is at iteration {iteration}"
            )
        if number == iteration and not finished:
            return None
    if len(lines) != iteration:
        return f"{path.name} is damaged: {len(lines)} rows, but the checkpoint is at iteration {iteration}"
    return None


def check_metrics(paths: list[Path], iteration: int, finished: bool) -> None:
    """Raises `ConfigError` for the first of `paths` whose rows do not match `iteration`."""
    for path in paths:
        problem = metrics_problem(path, iteration, finished)
        if problem is not None:
            raise ConfigError(
                f"invalid run directory {str(Path(path).parent)!r}: {problem} "
                "(allowed: one row per iteration up to the checkpoint's)"
            )


def first_missing(path: Path) -> Path | None:
    """The outermost of `path` and its parents that does not exist yet (None: `path` exists):
    what `coherent_jax.run.runs.prepare_output_dir` creates, and what `discard_new_dir` removes again."""
    path = Path(path)
    return next((p for p in [*reversed(path.parents), path] if not p.exists()), None)


def discard_new_dir(path: Path, created: Path | None) -> None:
    """Undoes a new run's start: removes `created` (from `first_missing`, taken before
    `prepare_output_dir`), or, when `path` existed (empty) before, only what is in it now."""
    if created is not None:
        shutil.rmtree(created, ignore_errors=True)
        return
    for entry in Path(path).iterdir():
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)


def set_aside(paths: list[Path]) -> tuple[int, list[Path]]:
    """Renames each existing one of `paths` (files or directories) to ``NAME.discarded-N``, one
    N for all, the smallest that renames over nothing; returns (N, the paths as renamed)."""
    present = [Path(p) for p in paths if Path(p).exists()]
    n = 1
    while any(p.with_name(f"{p.name}.discarded-{n}").exists() for p in present):
        n += 1
    moved = []
    for path in present:
        target = path.with_name(f"{path.name}.discarded-{n}")
        path.rename(target)
        moved.append(target)
    return n, moved
