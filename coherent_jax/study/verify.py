"""Does the code at HEAD still compute a study's finished cells bit for bit?

``python -m coherent_jax.study STUDY verify [CELL ...]`` re-runs each selected finished
cell's first iterations at HEAD: the cell's own sweep (its overrides and seeds, one
vmapped program, as `coherent_jax.study.cell.sweep_command` runs it) with ``total_steps``
cut to a few iterations, in a scratch directory that is deleted afterwards. Every value
the study's curves table (``STUDY_DIR/curves.csv.gz``) holds for those iterations is
then compared, as a float, with what the re-run logged. Per cell it reports one of

* ``bit-identical``: every compared value equal;
* ``differs from iteration N``: the first iteration whose logged value differs (only
  iterations that logged a return can be compared: an evaluation every ``eval_every``
  iterations, a training return once an episode has ended);

A difference is then told apart by the CPUs (`classify`): XLA compiles for the host's
vector extensions, and float32 sums round differently between them, so a cell made on
another CPU may differ for that reason alone. The verdict is one of

* ``bit-identical``;
* ``differs from iteration N on the same CPU``: the code (or a library's version, named)
  changed the bits; the entry names the last commit marked ``Changes bits:`` since the
  cell's (`last_changes_bits`), or says none is;
* ``not comparable: made on CPU X, this is CPU Y``: the CPUs differ (vendor, family,
  model, the extension XLA compiles for, or the XLA flags: `CPU_KEY`);
* ``differs from iteration N; the cell records too little of its CPU ...``: a cell made
  before runs recorded the CPU's identity (its name alone, "AMD EPYC", covers several).

with the commit and CPU the cell recorded (``commit unknown`` for a cell made before
runs recorded their commit), and writes that to a ``verify.json`` (`OUT`: the study's, or
for the suites of experiments/studies/ the one beside them, ``experiments/results/verify.json``),
one entry per cell (``STUDY/CELL``), merged with the entries already there. The reports mark
with † the cells whose entry says they differ.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coherent_jax.config.parse import modern_items
from coherent_jax.run.rundir import PROJECT_ROOT, VERSIONED_PACKAGES
from coherent_jax.study import curves
from coherent_jax.study.cell import PACKAGE_ROOT, Cell, cell_dir, cell_state, sweep_env

OUT = "verify.json"
# The fields of versions.json that must agree for bits to be comparable (coherent_jax.run.rundir).
NOT_COMPARABLE = "not comparable:"
CPU_KEY = ("cpu_vendor", "cpu_family", "cpu_model_number", "xla_cpu_isa", "xla_flags")
DEFAULT_ITERATIONS = 3
MARK = "†"
FOOTNOTE = (
    f"{MARK} The code at HEAD no longer reproduces this cell bit for bit "
    "(`python -m coherent_jax.study STUDY verify CELL`; its verify.json)."
)

Values = dict[tuple[str, int, str], list[float]]  # (point, env steps, metric) -> values in log order


def _values(rows: Sequence[curves.Row]) -> Values:
    """The logged values of a cell's curve rows, keyed by point, env steps and metric."""
    out: Values = {}
    for _, point, steps, *values in rows:
        for metric, v in zip(curves.METRICS, values, strict=True):
            if v is not None:
                out.setdefault((point, steps, metric), []).append(v)
    return out


def compare(committed: Values, now: Values, steps_per_iteration: int) -> dict[str, Any]:
    """Every committed value against the re-run's at the same point, env step and metric.

    A committed value the re-run did not log counts as a difference; values the re-run
    logged beyond the committed ones (its final evaluation) are not compared.
    """
    compared, first = 0, None
    for (point, steps, metric), values in sorted(committed.items(), key=lambda kv: (kv[0][1], kv[0])):
        got = now.get((point, steps, metric), [])
        for i, v in enumerate(values):
            compared += 1
            w = got[i] if i < len(got) else None
            if w != v and first is None:
                first = {
                    "iteration": steps // steps_per_iteration,
                    "env_steps": steps,
                    "point": point,
                    "metric": metric,
                    "committed": v,
                    "now": w,
                }
    iterations = sorted({s // steps_per_iteration for _, s, _ in committed})
    if not compared:
        result = "nothing to compare"
    elif first is None:
        result = "bit-identical"
    else:
        result = f"differs from iteration {first['iteration']}"
        if first["iteration"] == iterations[0] and iterations[0] > 1:
            result += " (the first compared)"
    return {
        "result": result,
        "values_compared": compared,
        "iterations_compared": iterations,
        "first_difference": first,
    }


def _yaml_int(path: Path, key: str) -> int:
    """An integer top-level key of a point's ``config.yaml`` (``key: value`` lines)."""
    for line in path.read_text().splitlines():
        k, _, v = line.partition(":")
        if k == key:
            return int(v.strip())
    raise KeyError(f"{key!r} not in {path}")


def steps_per_iteration(cell: Cell, study_dir: Path) -> int:
    """num_envs * unroll_length as the cell's first point resolved them."""
    config = curves.point_dirs(cell_dir(cell, study_dir) / "sweep")[0] / "config.yaml"
    return _yaml_int(config, "num_envs") * _yaml_int(config, "unroll_length")


def cell_provenance(cell: Cell, study_dir: Path) -> dict[str, Any]:
    """The commit and CPU a cell recorded (its sweep's ``versions.json``) and its resumes' commits;
    ``recorded``: the file's CPU fields and package versions, for `classify`."""
    sweep = cell_dir(cell, study_dir) / "sweep"
    try:
        v = json.loads((sweep / "versions.json").read_text())
    except (OSError, ValueError):
        v = {}
    resumed = []
    for path in sorted(sweep.glob("versions-resumed-*.json")):
        try:
            resumed.append(json.loads(path.read_text()).get("git_commit"))
        except (OSError, ValueError):
            resumed.append(None)
    return {
        "commit": v.get("git_commit") or "commit unknown",
        "dirty": v.get("git_dirty"),
        "cpu": v.get("cpu_model") or "CPU unknown",
        "cpu_vector_isa": v.get("cpu_vector_isa"),
        "resumed_at": resumed,
        "recorded": recorded(v),
    }


def recorded(versions: dict[str, Any]) -> dict[str, Any]:
    """The fields of a ``versions.json`` that decide whether two runs can be compared bit for
    bit: the CPU's (`CPU_KEY`, its name and stepping) and the versioned packages'."""
    keep = (*CPU_KEY, "cpu_model", "cpu_stepping", *VERSIONED_PACKAGES)
    return {k: versions[k] for k in keep if k in versions}


def cpu_label(v: dict[str, Any]) -> str:
    """A CPU as a reader tells it apart: name, vendor, family, model, stepping, XLA's extension."""
    name = v.get("cpu_model") or "unknown CPU"
    if not all(k in v for k in CPU_KEY):
        return f"{name} (identity not recorded)"
    flags = f", XLA_FLAGS={v['xla_flags']!r}" if v["xla_flags"] else ""
    return (
        f"{name} ({v['cpu_vendor']} family {v['cpu_family']} model {v['cpu_model_number']} "
        f"stepping {v.get('cpu_stepping')}, XLA for {v['xla_cpu_isa']}{flags})"
    )


def last_changes_bits(since: str | None, root: Path = PROJECT_ROOT) -> str:
    """The last commit after `since` (a cell's commit) whose message has a ``Changes bits:`` line,
    as ``HASH subject``; or why there is none to name."""
    if not since or since == "commit unknown":
        return "the cell's commit is unknown"
    try:
        done = subprocess.run(
            [
                "git",
                "-C",
                str(root),
                "log",
                "-1",
                "--format=%h %s",
                "--grep=^Changes bits:",
                f"{since}..HEAD",
            ],
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return "git is not available"
    if done.returncode != 0:
        return f"the cell's commit {since[:12]} is not in this checkout"
    return done.stdout.strip() or f"none since the cell's commit {since[:12]}"


def classify(
    entry: dict[str, Any], cell: dict[str, Any], here: dict[str, Any], commit: str | None
) -> dict[str, Any]:
    """The verdict of a compared cell (the module docstring's four), from what `compare` found,
    the cell's recorded CPU and versions (`recorded`) and this machine's; adds ``changes_bits``
    (`last_changes_bits`) to a difference on the same CPU."""
    if entry["result"] == "bit-identical" or not entry["result"].startswith("differs"):
        return entry
    if not all(k in cell for k in CPU_KEY):
        result = (
            f"{entry['result']}; the cell records too little of its CPU (only "
            f"{cell.get('cpu_model') or 'nothing'!r}) to tell a CPU change from a code change"
        )
        return {**entry, "result": result}
    if any(cell[k] != here.get(k) for k in CPU_KEY):
        return {
            **entry,
            "result": f"{NOT_COMPARABLE} made on CPU {cpu_label(cell)}, this is CPU {cpu_label(here)}",
        }
    result = f"{entry['result']} on the same CPU"
    versions = [
        f"{k} {here.get(k)} (the cell: {cell[k]})"
        for k in VERSIONED_PACKAGES
        if k in cell and cell[k] != here.get(k)
    ]
    if versions:
        result += ", with " + ", ".join(versions)
    return {**entry, "result": result, "changes_bits": last_changes_bits(commit)}


def rerun_command(cell: Cell, run_dir: Path, total_steps: int) -> list[str]:
    """The cell's sweep as `coherent_jax.study.cell.sweep_command` starts it, cut to ``total_steps``,
    quiet (its own ``progress`` and ``tensorboard``, which change no number, replaced)."""
    overrides = [
        f"total_steps={total_steps}" if o.startswith("total_steps=") else o
        for o in cell.overrides
        if not o.startswith(("progress=", "tensorboard="))
    ]
    return [
        sys.executable,
        "-m",
        "coherent_jax.sweep",
        *modern_items(overrides, note=False),
        f"seeds={cell.seeds}",
        f"run_dir={run_dir}",
        "progress=false",
        "tensorboard=false",
    ]


def verify_cell(
    cell: Cell,
    study_dir: Path,
    iterations: int = DEFAULT_ITERATIONS,
    log=print,
    cwd: Path = PACKAGE_ROOT,
    command: str = "",
) -> dict[str, Any]:
    """Re-runs a finished cell's first iterations at HEAD and compares them with its committed curves.

    At least ``iterations`` iterations, and as many as it takes to reach the first
    value the committed table holds (an evaluation every ``eval_every`` iterations).
    The sweep runs in ``cwd`` (the study file's folder: a user's env file is named
    relative to it); ``command`` is what the entry records as the way to repeat it.
    """
    spi = steps_per_iteration(cell, study_dir)
    table = [r for r in curves.read_table(curves.table_path(study_dir)) if r[0] == cell.name]
    if not table:
        raise ValueError(f"cell {cell.name!r} has no rows in {curves.table_path(study_dir)}")
    first_logged = min(r[2] for r in table) // spi
    n = max(iterations, first_logged)
    committed = _values([r for r in table if r[2] <= n * spi])
    with tempfile.TemporaryDirectory(prefix="verify-") as scratch:
        cmd = rerun_command(cell, Path(scratch) / "sweep", n * spi)
        log(f"[verify] {cell.suite} {cell.name}: {n} iterations: {' '.join(cmd[1:-3])} ...")
        t0 = time.time()
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, env=sweep_env(), check=False)
        wall = time.time() - t0
        if done.returncode != 0:
            tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
            raise RuntimeError(f"the re-run of {cell.name!r} exited {done.returncode}: {tail[0]}")
        now = _values(curves.cell_rows(cell.name, Path(scratch) / "sweep"))
        # What the re-run recorded of its code and machine (as every sweep does).
        here = json.loads((Path(scratch) / "sweep" / "versions.json").read_text())
    provenance = cell_provenance(cell, study_dir)
    verdict = classify(
        compare(committed, now, spi), provenance["recorded"], recorded(here), provenance["commit"]
    )
    return {
        **verdict,
        "cell": provenance,
        "verified_at": {
            "commit": here.get("git_commit"),
            "dirty": here.get("git_dirty"),
            "cpu": here.get("cpu_model"),
            "cpu_vector_isa": here.get("cpu_vector_isa"),
            "recorded": recorded(here),
            "date": time.strftime("%Y-%m-%d"),
        },
        "iterations_run": n,
        "wall_s": round(wall, 1),
        "command": command or f"python -m coherent_jax.study {cell.suite} verify {cell.name}",
    }


def line(name: str, entry: dict[str, Any]) -> str:
    """One cell's result in one line: the verdict, the cell's commit and CPU."""
    c = entry["cell"]
    commit = c["commit"] if c["commit"] == "commit unknown" else f"commit {c['commit'][:12]}"
    bits = f"; last 'Changes bits:' commit: {entry['changes_bits']}" if entry.get("changes_bits") else ""
    return (
        f"{name}: {entry['result']} ({commit}, {c['cpu']}; {entry['values_compared']} values compared{bits})"
    )


def load(folder: Path) -> dict[str, Any]:
    """``FOLDER/verify.json``'s entries by ``STUDY/CELL``; none if it does not exist."""
    path = Path(folder) / OUT
    return json.loads(path.read_text())["cells"] if path.is_file() else {}


def save(folder: Path, entries: dict[str, Any]) -> Path:
    """Writes the entries (sorted, atomically) to ``FOLDER/verify.json``."""
    path = Path(folder) / OUT
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps({"cells": dict(sorted(entries.items()))}, indent=1) + "\n")
    tmp.replace(path)
    return path


def mark(cell: Cell, entries: dict[str, Any]) -> str:
    """`MARK` (with a leading space) if the cell's verify entry says HEAD does not reproduce it."""
    entry = entries.get(f"{cell.suite}/{cell.name}")
    return f" {MARK}" if entry and entry["result"].startswith("differs") else ""


def footnote(cells: Sequence[Cell], entries: dict[str, Any]) -> list[str]:
    """`FOOTNOTE` (one line) under a table in which `mark` marked a cell, else nothing."""
    return ["", FOOTNOTE] if any(mark(c, entries) for c in cells) else []


def run(
    cells: Sequence[Cell],
    study_dir: Path,
    iterations: int = DEFAULT_ITERATIONS,
    record: Path | None = None,
    cwd: Path = PACKAGE_ROOT,
    command: str = "",
) -> int:
    """``verify``: each finished cell in turn, its entry saved to ``RECORD/verify.json`` (default:
    the study's folder) as soon as it is known; ``command`` (with ``{cell}``) is how to repeat one.

    Exit status 0 when every verified cell is bit-identical or not comparable (made on another
    CPU: no verdict on the code), 1 when one differs or is not finished, 2 for bad input.
    """
    record = Path(study_dir) if record is None else Path(record)
    if iterations < 1:
        print(
            f"error: invalid value for '--iterations': {iterations} (allowed: an integer >= 1)",
            file=sys.stderr,
        )
        return 2
    status = 0
    for cell in cells:
        name = f"{cell.suite}/{cell.name}"
        if cell_state(cell, study_dir) != "done":
            print(f"{name}: not finished, not verified")
            status = 1
            continue
        try:
            entry = verify_cell(cell, study_dir, iterations, cwd=cwd, command=command.format(cell=cell.name))
        except (RuntimeError, ValueError, OSError, KeyError, IndexError) as exc:
            print(f"{name}: not verified: {exc}", file=sys.stderr)
            status = 1
            continue
        save(record, {**load(record), name: entry})
        print(line(name, entry), flush=True)
        status |= not (entry["result"] == "bit-identical" or entry["result"].startswith(NOT_COMPARABLE))
    return status


def provenance_lines(cells: Sequence[Cell], study_dirs: dict[str, Path]) -> list[str]:
    """The commits and CPUs the cells' numbers came from, with how many cells each.

    Read from each cell's ``sweep/versions.json`` and the ``versions-resumed-*.json`` a resume
    on another commit or machine left beside it; a cell (or part of one) recorded before
    these were kept counts as "not recorded", one run outside a git checkout as "no git
    checkout". A cell computed in parts counts once under each. ``study_dirs``: each cell's
    study (`Cell.suite`) -> its folder.
    """
    commits: dict[str, int] = defaultdict(int)
    cpus: dict[str, int] = defaultdict(int)
    for cell in cells:
        cell_commits, cell_cpus = set(), set()
        for path in sorted((cell_dir(cell, study_dirs[cell.suite]) / "sweep").glob("versions*.json")):
            try:
                v = json.loads(path.read_text())
            except (OSError, ValueError):
                continue
            commit, dirty = v.get("git_commit"), " with uncommitted changes" if v.get("git_dirty") else ""
            isa = v.get("cpu_vector_isa") or "no AVX/SSE4.2"
            cell_commits.add(
                "not recorded"
                if "git_commit" not in v
                else f"`{commit[:12]}`{dirty}"
                if commit
                else "no git checkout"
            )
            cell_cpus.add(
                f"{v['cpu_model'] or 'unknown CPU'} ({isa})" if "cpu_model" in v else "not recorded"
            )
        for label in cell_commits or {"not recorded"}:
            commits[label] += 1
        for label in cell_cpus or {"not recorded"}:
            cpus[label] += 1

    def counts(table: dict[str, int]) -> str:
        return ", ".join(f"{k} ({n} cell{'s' if n > 1 else ''})" for k, n in sorted(table.items()))

    return [f"Computed at commits: {counts(commits)}; on CPUs: {counts(cpus)}.", ""]
