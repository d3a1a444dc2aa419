"""The curves a study's report reads, one compressed table per study: ``STUDY_DIR/curves.csv.gz``.

A sweep writes each point's learning curve to its ``metrics.jsonl``: every metric of
every iteration, about 160 kB per seed of 1M env steps. The report reads four of its
columns: the evaluation return (`EVAL`), the training return (`TRAIN`, for a sparse
task's first reward) and, on a task whose termination is its goal (MountainCar), the
fractions of evaluation and training episodes that reached it (`EVAL_GOAL`,
`TRAIN_GOAL`). A study's table holds those of every point of its finished cells, one
row per ``metrics.jsonl`` row that logged any of them::

    cell,point,env_steps,eval/episode_return,train/episode_return,eval/goal_reached,train/goal_reached
    halfcheetah/ppo/action,p000-seed=0,4096,,-286.61676025390625,,

A table written before the goal columns existed (`LEGACY_HEADER`) reads as one whose
goal fields are all empty.

An empty field is a metric that row did not log; a value is written as
``metrics.jsonl`` wrote it (Python's shortest repr of the float, which reads back to
the same float). Rows are sorted by cell, point and env steps (rows of equal env
steps keep their order in the log), and the gzip stream carries no time stamp, so the
same logs always give the same bytes.

What git keeps of a cell is `committed_files`: its specification, its sweep's summary
and small records, each point's ``config.yaml`` and ``summary.json``, and its study's
table. The per-seed logs stay where the cell ran (``experiments/results/.gitignore``;
``experiments/README.md`` names the commit that holds those of the earlier cells).
``python -m coherent_jax.study curves STUDY_DIR`` rebuilds a table from the local logs.
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import gzip
import io
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from coherent_jax.run.rundir import read_metrics

TABLE = "curves.csv.gz"
EVAL = "eval/episode_return"
TRAIN = "train/episode_return"
EVAL_GOAL = "eval/goal_reached"
TRAIN_GOAL = "train/goal_reached"
METRICS = (EVAL, TRAIN, EVAL_GOAL, TRAIN_GOAL)  # the returns, then the goal fractions
HEADER = ("cell", "point", "env_steps", *METRICS)
LEGACY_HEADER = HEADER[:5]  # the returns only
LOG = "metrics.jsonl"

# The small files of a cell that git keeps, beside its suite's table.
CELL_FILES = ("cell.json",)
SWEEP_FILES = ("config.yaml", "grid.json", "sweep.csv", "sweep.json", "versions.json")
RESUMED_VERSIONS = "versions-resumed-*.json"
POINT_FILES = ("config.yaml", "summary.json")

Row = tuple[Any, ...]  # (cell, point, env steps, *METRICS): str, str, int, then float or None each


def table_path(study_dir: Path) -> Path:
    """``STUDY_DIR/curves.csv.gz``."""
    return Path(study_dir) / TABLE


def point_dirs(sweep: Path) -> list[Path]:
    """A sweep's point (run) directories, sorted: those holding a ``config.yaml``."""
    if not sweep.is_dir():
        return []
    return sorted(p for p in sweep.iterdir() if (p / "config.yaml").exists())


def _value(x: Any) -> float | None:
    return None if x is None else float(x)


def log_rows(cell: str, point: str, rows: Iterable[dict[str, Any]]) -> list[Row]:
    """The table's rows of one point from its ``metrics.jsonl`` rows (in their order)."""
    out = []
    for r in rows:
        values = tuple(_value(r.get(m)) for m in METRICS)
        if any(v is not None for v in values):
            out.append((cell, point, int(r["env_steps"]), *values))
    return out


def cell_rows(cell: str, sweep: Path) -> list[Row]:
    """The table's rows of a cell from its points' local ``metrics.jsonl`` (none without logs;
    read as `coherent_jax.plot.load_run` reads them)."""
    rows: list[Row] = []
    for point in point_dirs(sweep):
        if (point / LOG).is_file():
            rows += log_rows(cell, point.name, read_metrics(point / LOG))
    return rows


def _field(x: float | None) -> str:
    return "" if x is None else repr(x)


def encode(rows: Iterable[Row]) -> bytes:
    """The table's bytes: CSV sorted by (cell, point, env steps), gzip without time stamp."""
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(HEADER)
    for cell, point, steps, *values in sorted(rows, key=lambda r: (r[0], r[1], r[2])):
        writer.writerow([cell, point, str(steps), *map(_field, values)])
    return gzip.compress(text.getvalue().encode(), compresslevel=9, mtime=0)


def decode(data: bytes) -> list[Row]:
    """The rows of a table's bytes (`encode`'s inverse)."""
    reader = csv.reader(io.StringIO(gzip.decompress(data).decode()))
    header = tuple(next(reader, None) or ())
    if header not in (HEADER, LEGACY_HEADER):
        raise ValueError(f"not a curves table: header {list(header)} (expected {list(HEADER)})")
    pad = (None,) * (len(HEADER) - len(header))
    return [(c, p, int(s), *(float(v) if v else None for v in vals), *pad) for c, p, s, *vals in reader]


def read_table(path: Path) -> list[Row]:
    """A table's rows; none if it does not exist."""
    return decode(Path(path).read_bytes()) if Path(path).is_file() else []


_CACHE: dict[Path, tuple[tuple[int, int], dict[tuple[str, str], list[dict[str, Any]]]]] = {}


def table_runs(path: Path) -> dict[tuple[str, str], list[dict[str, Any]]]:
    """(cell, point) -> its rows as ``metrics.jsonl`` rows (env steps and the metrics
    it logged); read once per version of the file."""
    path = Path(path)
    if not path.is_file():
        return {}
    stat = path.stat()
    key = (stat.st_mtime_ns, stat.st_size)
    if path not in _CACHE or _CACHE[path][0] != key:
        runs: dict[tuple[str, str], list[dict[str, Any]]] = {}
        for cell, point, steps, *values in read_table(path):
            logged = {m: v for m, v in zip(METRICS, values, strict=True) if v is not None}
            runs.setdefault((cell, point), []).append({"env_steps": steps, **logged})
        _CACHE[path] = (key, runs)
    return _CACHE[path][1]


def write_table(path: Path, rows: Iterable[Row]) -> bool:
    """Writes the table atomically when its bytes change; whether they did."""
    data = encode(rows)
    if path.is_file() and path.read_bytes() == data:
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    return True


@contextlib.contextmanager
def _locked(directory: Path) -> Iterator[None]:
    """Holds an exclusive lock on `directory` (cells of a suite finish in parallel processes;
    locking the directory itself leaves no lock file behind)."""
    directory.mkdir(parents=True, exist_ok=True)
    fd = os.open(directory, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def update_table(study_dir: Path, cells: Iterable[str], prune: bool = False) -> Path:
    """Replaces the rows of `cells` (names in the study) with those of their local logs; a
    cell without logs keeps its rows. With `prune`, cells not named lose theirs."""
    path = table_path(study_dir)
    names = sorted(set(cells))
    with _locked(path.parent):
        new = {name: cell_rows(name, Path(study_dir) / name / "sweep") for name in names}
        fresh = {name for name, rows in new.items() if rows}
        keep = [r for r in read_table(path) if r[0] not in fresh and (not prune or r[0] in names)]
        write_table(path, keep + [r for name in sorted(fresh) for r in new[name]])
    return path


def tabled_cells(study_dir: Path) -> set[str]:
    """The names of the cells the study's table holds rows of."""
    return {r[0] for r in read_table(table_path(study_dir))}


def finished_cells(study_dir: Path) -> list[str]:
    """Names of the cells under `study_dir` whose sweep finished."""
    root = Path(study_dir)
    return sorted(
        spec.parent.relative_to(root).as_posix()
        for spec in root.glob("**/cell.json")
        if (spec.parent / "sweep" / "sweep.json").is_file()
    )


def build(study_dir: Path) -> Path:
    """The study's table from the logs of its finished cells (a finished cell whose logs
    are absent keeps its rows; rows of cells that are not finished are dropped)."""
    return update_table(study_dir, finished_cells(study_dir), prune=True)


def committed_files(cell: Path, table: Path) -> list[Path]:
    """What git keeps of the finished cell in directory `cell`: its small files (`CELL_FILES`,
    `SWEEP_FILES`, `RESUMED_VERSIONS`, each point's `POINT_FILES`) and its study's `table`,
    those that exist."""
    sweep = cell / "sweep"
    files = [cell / f for f in CELL_FILES] + [sweep / f for f in SWEEP_FILES]
    files += sorted(sweep.glob(RESUMED_VERSIONS))  # a cell resumed on another machine or commit
    files += [point / f for point in point_dirs(sweep) for f in POINT_FILES]
    return [f for f in [*files, table] if f.is_file()]
