"""Running a study's cells to the end: an executor of cell sweeps, its one progress display,
the study's folder (its record and lock) and what a finished cell leaves.

An `Executor` starts a cell's sweep (`Job`) and reports the jobs that ended; the study's loop
(`run_cells`) keeps its slots full, finishes each ended cell (its rows in the study's curves
table, its carry file dropped) and redraws the progress line (cells done, running, left; the
compute left from `coherent_jax.study.cost`). `LocalExecutor` runs each sweep as a worker
process on this machine; another executor implements the same three methods
(`coherent_jax.study.ray_executor.RayExecutor`: each sweep a Ray task on a cluster). What git
keeps of a study is committed here too: a finished cell's small files (``commit=true``,
`commit_cell`), a stopped cell's state as its carry file (``pack=true``, `pack_cells`;
`coherent_jax.study.carry`).

A study's folder holds ``study.json`` (its name, the folder its sweeps run in, the command,
its cells, metrics and claims: what ``report`` reads) and, while the study runs,
``study.lock`` (an ``flock``: one study process at a time). A study killed at any point
is continued by the same command: finished cells are kept, a stopped one resumes its sweep
from its checkpoint (`coherent_jax.study.cell.sweep_command`), and a cell's sweep ends with
the study's process (SIGTERM, which checkpoints it).
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import IO, Protocol

from coherent_jax.study import carry, curves
from coherent_jax.study.cell import (
    LOG,
    PID_FILE,
    Cell,
    StudyError,
    cell_dir,
    cell_state,
    check_cell_dir,
    prepare,
    progress,
    running_pid,
    sweep_env,
)
from coherent_jax.study.cost import estimated_seconds, finished_cells, start_seconds

RECORD = "study.json"
LOCK = "study.lock"
# What a study's folder holds besides its cells' task folders.
STUDY_FILES = (RECORD, LOCK, curves.TABLE, "REPORT.md", "figures", "verify.json", "tune.json")
GIB = 2**30
CELL_MEMORY = 2 * GIB  # what one cell's sweep takes at most, for the default number of workers
PR_SET_PDEATHSIG = 1  # prctl(2): the signal a process gets when its parent ends


@dataclasses.dataclass(frozen=True)
class Job:
    """One cell's sweep: its command, the folder it runs in, its log and its pid file."""

    cell: Cell
    command: tuple[str, ...]
    cwd: Path
    log: Path
    pid_file: Path


class Executor(Protocol):
    """What runs the cells' sweeps: ``slots`` at a time."""

    slots: int

    def start(self, job: Job) -> None:
        """Starts `job` (returns at once)."""

    def wait(self, timeout: float) -> list[tuple[Job, int]]:
        """The jobs that ended (with their exit status) since the last call, waiting at most
        `timeout` seconds for one."""

    def stop(self) -> None:
        """Ends every running job (SIGTERM: a sweep checkpoints and stops) and waits for them."""


# Runs a sweep so that it ends with the study's process, however that ends: Linux's
# PR_SET_PDEATHSIG (SIGTERM: the sweep checkpoints and stops) set before the sweep's exec
# (no pre-exec hook in a parent that may hold threads); a study already gone ends it at once.
# Elsewhere a killed study's sweeps run on to their end, and the study waits for them.
WITH_PARENT = (
    "import ctypes, os, signal, sys\n"
    "try:\n"
    f"    ctypes.CDLL(None).prctl({PR_SET_PDEATHSIG}, signal.SIGTERM)\n"
    "except (OSError, AttributeError):\n"
    "    pass\n"
    "if os.getppid() != int(sys.argv[1]):\n"
    "    sys.exit(128 + signal.SIGTERM)\n"
    "os.execv(sys.argv[2], sys.argv[2:])\n"
)


class LocalExecutor:
    """Each cell's sweep as a worker process on this machine, `workers` at a time."""

    def __init__(self, workers: int) -> None:
        self.slots = workers
        self.running: dict[int, tuple[Job, subprocess.Popen]] = {}

    def start(self, job: Job) -> None:
        with open(job.log, "a") as log:
            command = [sys.executable, "-c", WITH_PARENT, str(os.getpid()), *job.command]
            proc = subprocess.Popen(
                command, stdout=log, stderr=subprocess.STDOUT, cwd=job.cwd, env=sweep_env()
            )
        job.pid_file.write_text(f"{proc.pid}\n")
        self.running[proc.pid] = (job, proc)

    def wait(self, timeout: float) -> list[tuple[Job, int]]:
        deadline = time.monotonic() + timeout
        while True:
            ended = [(pid, job, proc.poll()) for pid, (job, proc) in self.running.items()]
            ended = [(pid, job, code) for pid, job, code in ended if code is not None]
            if ended or not self.running or time.monotonic() >= deadline:
                break
            time.sleep(0.2)
        for pid, job, _ in ended:
            del self.running[pid]
            job.pid_file.unlink(missing_ok=True)
        return [(job, code) for _, job, code in ended]

    def stop(self) -> None:
        for _, proc in self.running.values():
            proc.send_signal(signal.SIGTERM)
        for job, proc in self.running.values():
            proc.wait()
            job.pid_file.unlink(missing_ok=True)
        self.running.clear()


def default_workers() -> int:
    """As many cells at a time as fit this machine: one per core, and `CELL_MEMORY` each."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    try:
        meminfo = Path("/proc/meminfo").read_text().split("MemAvailable:")[1].split()[0]
        memory = int(meminfo) * 1024 // CELL_MEMORY
    except (OSError, IndexError, ValueError):
        memory = cores
    return max(1, min(cores, memory))


# ------------------------------------------------------------------ the study's folder
def check_folder(out: Path, name: str, cells: Sequence[Cell]) -> None:
    """Refuses a folder that holds another study, or files of none, or a cell of another
    specification (`coherent_jax.study.cell.check_cell_dir`)."""
    if out.exists() and not out.is_dir():
        raise StudyError(
            f"invalid value for 'out': {str(out)!r} is not a folder (allowed: a folder, new or this study's)"
        )
    record = out / RECORD
    if record.is_file():
        try:
            held = json.loads(record.read_text()).get("name")
        except (OSError, ValueError, AttributeError):
            held = None
        if held != name:
            raise StudyError(
                f"invalid value for 'out': {str(out)!r} holds study {held!r} (allowed: a new folder, "
                f"or study {name!r}'s own)"
            )
    elif out.is_dir():
        mine = {c.name.split("/", 1)[0] for c in cells} | set(STUDY_FILES)
        other = sorted(p.name for p in out.iterdir() if p.name not in mine)
        if other:
            raise StudyError(
                f"invalid value for 'out': {str(out)!r} holds {other[0]!r}, no part of study {name!r} "
                "(allowed: a new or empty folder, or this study's own)"
            )
    for cell in cells:
        check_cell_dir(cell, out)


@contextlib.contextmanager
def holding(out: Path) -> Iterator[None]:
    """The study's lock: one study process at a time in its folder."""
    out.mkdir(parents=True, exist_ok=True)
    fd = os.open(out / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "another process"
            raise StudyError(
                f"study folder {str(out)!r} is in use by process {holder} "
                "(allowed: one study process at a time; wait for it or stop it)"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def write_record(out: Path, record: dict) -> None:
    tmp = out / (RECORD + ".tmp")
    tmp.write_text(json.dumps(record, indent=1) + "\n")
    os.replace(tmp, out / RECORD)


# ------------------------------------------------------------------ the loop
class Progress:
    """The one progress line: cells done, running, left (and failed), the compute left."""

    def __init__(self, name: str, stream: IO[str], workers: int) -> None:
        self.name, self.stream, self.workers = name, stream, workers
        self.tty = stream.isatty()
        self.last, self.shown_at = "", 0.0

    def show(self, counts: dict[str, int], seconds_left: float, force: bool = False) -> None:
        text = (
            f"[study] {self.name}: {counts['done']} done, {counts['running']} running, "
            f"{counts['left']} left" + (f", {counts['failed']} failed" if counts["failed"] else "")
            + f"; about {_duration(seconds_left)} left"
        )  # fmt: skip
        changed = text.split(";")[0] != self.last.split(";")[0]
        if not (force or changed or time.monotonic() - self.shown_at > 60):
            return
        self.last, self.shown_at = text, time.monotonic()
        self.stream.write(("\r\x1b[2K" + text) if self.tty else text + "\n")
        self.stream.flush()

    def say(self, line: str) -> None:
        """A line of its own above the progress line."""
        self.stream.write(("\r\x1b[2K" if self.tty else "") + line + "\n")
        if self.tty and self.last:
            self.stream.write(self.last)
        self.stream.flush()


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


def finish_cell(cell: Cell, out: Path) -> None:
    """A finished cell's rows in the study's curves table; its carry file dropped (a tracked one
    is left deleted, for whoever commits the results)."""
    curves.update_table(out, [cell.name])
    carry.drop(cell_dir(cell, out), out)


def _wait_for_orphans(cells: Sequence[Cell], out: Path, display: Progress) -> None:
    """Sweeps a killed study left running end with it (SIGTERM: they checkpoint); waits for them."""
    orphans = [c for c in cells if running_pid(c, out) is not None]
    if orphans:
        display.say(f"[study] waiting for {len(orphans)} sweep(s) of a stopped study to checkpoint and end")
    while any(running_pid(c, out) is not None for c in orphans):
        time.sleep(0.5)
    for c in orphans:
        (cell_dir(c, out) / PID_FILE).unlink(missing_ok=True)


def _seconds_left(
    pending: Sequence[Cell], active: Sequence[Cell], out: Path, workers: int, probed: Mapping[str, float]
) -> float:
    """The compute the cells not done still need (with the start, compile and evaluations of
    those not started), over the cells that run at a time."""
    kin = finished_cells(out.parent)
    cells = [*pending, *active]
    need = sum(estimated_seconds(c, out, probed, kin) + start_seconds(c, out, kin) for c in cells)
    return need / max(1, min(workers, len(pending) + len(active)))


def run_cells(
    cells: Sequence[Cell],
    out: Path,
    cwd: Path,
    executor: Executor,
    stream: IO[str] | None = None,
    on_done: Callable[[Cell], None] | None = None,
    probed: Mapping[str, float] | None = None,
) -> list[str]:
    """Runs every cell not done, `executor.slots` at a time, to the end (each finished cell
    through `finish_cell`, then `on_done`); the names of those whose sweep failed. The time left
    is estimated by `coherent_jax.study.cost.estimated_seconds` (``probed``: a plan's rates). A
    KeyboardInterrupt stops the running sweeps (checkpointed) first."""
    stream = sys.stdout if stream is None else stream
    display = Progress(cells[0].suite if cells else out.name, stream, executor.slots)
    _wait_for_orphans(cells, out, display)
    tabled = curves.tabled_cells(out)
    for cell in cells:  # a finished cell whose rows were not written (its study killed in between)
        if cell_state(cell, out) == "done" and cell.name not in tabled:
            finish_cell(cell, out)
    pending = [c for c in cells if cell_state(c, out) != "done"]
    active: dict[str, Cell] = {}
    failed: list[str] = []

    def counts() -> dict[str, int]:
        done = len(cells) - len(pending) - len(active) - len(failed)
        return {"done": done, "running": len(active), "left": len(pending), "failed": len(failed)}

    try:
        while pending or active:
            while pending and len(active) < executor.slots:
                cell = pending.pop(0)
                command = prepare(cell, out)
                d = cell_dir(cell, out)
                executor.start(Job(cell, tuple(command), cwd, d / LOG, d / PID_FILE))
                active[cell.name] = cell
                display.say(f"[study] {cell.name}: started")
            for job, code in executor.wait(timeout=5.0):
                cell = active.pop(job.cell.name)
                if code == 0 and cell_state(cell, out) == "done":
                    finish_cell(cell, out)
                    if on_done is not None:
                        on_done(cell)
                    display.say(f"[study] {cell.name}: done")
                else:
                    failed.append(cell.name)
                    display.say(f"[study] {cell.name}: failed (exit {code}; see {cell_dir(cell, out) / LOG})")
            left = _seconds_left(pending, list(active.values()), out, executor.slots, probed or {})
            display.show(counts(), left)
    except KeyboardInterrupt:
        executor.stop()
        display.say("[study] stopped: the running cells checkpointed; the same command continues")
        raise
    display.show(counts(), 0.0, force=True)
    if display.tty:
        stream.write("\n")
    return failed


# ------------------------------------------------------------------ what git keeps
def _git_commit(root: Path, files: Sequence[str], message: str) -> None:
    subprocess.run(["git", "-C", str(root), "add", "--", *files], check=True)
    subprocess.run(["git", "-C", str(root), "commit", "-q", "-m", message, "--", *files], check=False)


def commit_cell(cell: Cell, study_dir: Path) -> None:
    """Commits a finished cell's compact results: its study's curves table, updated from the
    cell's per-seed logs, and the cell's small files (`curves.committed_files`). The logs
    themselves stay local (experiments/results/.gitignore)."""
    table = curves.update_table(study_dir, [cell.name])
    files = [str(f) for f in curves.committed_files(cell_dir(cell, study_dir), table)]
    files += carry.drop(cell_dir(cell, study_dir), study_dir)
    _git_commit(study_dir, files, f"results: {cell.suite} {cell.name}")


def pack_cells(cells: Sequence[Cell], study_dir: Path, commit: bool) -> int:
    """``pack=true``: each stopped cell's carry file; none if a selected cell is running (exit 2).
    A cell that cannot be carried (too large: SAC) is named and passed over (exit 1)."""
    running = [c.name for c in cells if cell_state(c, study_dir) == "running"]
    if running:
        print(
            f"error: cell {running[0]!r} is running (allowed: stopped cells; SIGTERM checkpoints it)",
            file=sys.stderr,
        )
        return 2
    packed, failed = [], 0
    for cell in (c for c in cells if cell_state(c, study_dir) == "stopped"):
        try:
            packed.append(str(carry.pack(cell_dir(cell, study_dir))))
        except carry.CarryError as exc:
            print(f"error: {exc}", file=sys.stderr)
            failed += 1
            continue
        size = Path(packed[-1]).stat().st_size / 1e6
        print(f"[study] {cell.name}: {100 * progress(cell, study_dir)[0]:.1f}% done, packed in {size:.2f} MB")
    if commit and packed:
        _git_commit(study_dir, packed, f"results: carry {len(packed)} stopped cells of {cells[0].suite}")
    return 1 if failed else 0
