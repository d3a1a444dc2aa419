"""A run's (or a sweep's) directory: what it holds beside the checkpoint, and who writes in it.

* Its files are written atomically (`atomic_write`: a temporary file, flushed, then renamed).
* Its kind: a sweep's root holds ``grid.json`` beside its shared ``config.yaml``; each point
  is a sub-directory with a single run's ``config.yaml`` and rows but no checkpoint (the
  sweep keeps one for the whole grid). `refuse_sweep_for_train` and `sweep_points` let
  ``train`` and ``evaluate`` say which command or directory to use instead of failing
  later on a shape mismatch.
* A new one is made writable before any work (`prepare_output_dir`); `first_missing` and
  `discard_new_dir` remove it again when its start fails (W&B not starting).
* One process at a time: the process that trains in a directory holds an exclusive
  ``flock`` on ``DIR/run.lock``, a file holding its PID, from before it writes anything
  until it exits; it removes the file when it is done. A second process, starting or
  resuming in the same directory, is refused in one line naming the holder's PID. The
  kernel drops a ``flock`` when its holder dies, so the file a SIGKILLed process leaves
  behind is a stale lock: the next process takes it over (and writes its own PID into
  it). A lock file is unlinked before it is unlocked, and a process that locked a file
  checks that it is still the one at ``DIR/run.lock`` (else it retries), so two
  processes can never both hold the lock of one directory.
* Its rows, ``metrics.jsonl``: `metrics_problem` compares them with the checkpoint's
  iteration (a file truncated or damaged, a line that is not a metrics row, would
  otherwise be reported as complete, or have its lost rows silently skipped by a resume);
  `set_aside` keeps the rows of a resume that found no checkpoint (it starts over) as
  ``metrics.jsonl.discarded-N``.
* Where its numbers came from, ``versions.json`` (`record_versions`): Python, the platform,
  the versions of the packages a run's numbers depend on, and

  - ``git_commit``, ``git_dirty``: the commit of the checkout this package was imported
    from, and whether its tracked files differed from it. Untracked files do not count,
    nor do the results under `RESULTS_DATA` (experiments/results/): a suite updates its
    committed curves as each cell finishes, before they are committed, and that is data,
    not code. Both null outside a git checkout of the project (an installed wheel, no
    ``git``).
  - ``cpu_model``: the processor's name (``model name`` of ``/proc/cpuinfo``, else
    `platform.processor`).
  - ``cpu_vendor``, ``cpu_family``, ``cpu_model_number``, ``cpu_stepping``: the
    processor's identity (``vendor_id``, ``cpu family``, ``model``, ``stepping``); the
    name alone ("AMD EPYC") covers processors of several generations.
  - ``cpu_vector_isa``: the widest vector extension the CPU reports (``avx512f``, ``avx2``,
    ``avx``, ``sse4_2``; null if none of these or unknown). XLA compiles for the host's
    extensions, so two machines at different levels can round float32 sums differently.
  - ``xla_cpu_isa``: the extension XLA compiles for (`xla_cpu_isa`): the host's, capped by
    ``--xla_cpu_max_isa`` in ``XLA_FLAGS``; ``xla_flags``: ``XLA_FLAGS`` as the run saw it.

  The provenance is best effort: a failure gives null, never an error.

The checkpoint and the stored config are `coherent_jax.run.checkpoint`'s. No JAX here.
"""

from __future__ import annotations

import contextlib
import fcntl
import importlib.metadata
import json
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

from coherent_jax.config import ConfigError

PREFIX = "[coherent_jax]"  # starts every line the command-line programs print
CONFIG = "config.yaml"
METRICS = "metrics.jsonl"
VERSIONS = "versions.json"
GRID = "grid.json"  # a sweep's grid, in its root directory
LOCK = "run.lock"
VERSIONED_PACKAGES = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "brax", "flax", "optax", "numpy", "chex")
# Widest first: the first of these in the CPU's flags is its level.
VECTOR_LEVELS = ("avx512f", "avx2", "avx", "sse4_2")
XLA_ISA = {"avx512f": "AVX512", "avx2": "AVX2", "avx": "AVX", "sse4_2": "SSE4_2"}  # XLA's names
ISA_ORDER = ("SSE4_2", "AVX", "AVX2", "AVX512")  # narrowest first
CPUINFO_FIELDS = ("model name", "vendor_id", "cpu family", "model", "stepping")
PROJECT_ROOT = Path(__file__).resolve().parents[2]  # coherent_jax/run/rundir.py -> the checkout
#: tracked results data that `git_state` does not count as a change of the checkout
RESULTS_DATA = "experiments/results"


def atomic_write(path: Path, data: bytes) -> None:
    """Writes `data` to `path` through a temporary file and a rename (POSIX-atomic)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


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


def prepare_output_dir(path: Path, key: str = "run_dir") -> Path:
    """Creates `path` as a new or empty, writable directory; raises `ConfigError` in one line otherwise.

    Called before any work, so a read-only or invalid location is refused at once
    rather than after the first hour of training; a directory created here is removed
    again when it turns out unusable.
    """
    path = Path(path)
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        hint = f"; to continue the run in it: resume={path}" if (path / CONFIG).is_file() else ""
        raise ConfigError(
            f"invalid value for {key!r}: {str(path)!r} (allowed: a new or empty directory{hint})"
        )
    created = []
    try:
        for parent in [*reversed(path.parents), path]:
            if not parent.exists():
                parent.mkdir()
                created.append(parent)
        probe = path / ".write-check"
        probe.write_bytes(b"")
        probe.unlink()
    except (OSError, ValueError) as exc:
        for made in reversed(created):
            made.rmdir()
        reason = getattr(exc, "strerror", None) or str(exc)
        raise ConfigError(
            f"invalid value for {key!r}: {str(path)!r} cannot be written ({reason}) "
            "(allowed: a new or empty directory in a writable location)"
        ) from None
    return path


def first_missing(path: Path) -> Path | None:
    """The outermost of `path` and its parents that does not exist yet (None: `path` exists):
    what `prepare_output_dir` creates, and what `discard_new_dir` removes again."""
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


def _read_pid(fd: int) -> str:
    os.lseek(fd, 0, os.SEEK_SET)
    text = os.read(fd, 64).decode(errors="replace").strip()
    return text if text.isdigit() else "unknown"


def _in_use(directory: Path, key: str, pid: str) -> Exception:
    return ConfigError(
        f"invalid value for {key!r}: {str(directory)!r} is in use by process {pid} "
        f"(allowed: a directory no running process trains in; {LOCK} names the holder)"
    )


class RunLock:
    """A held lock; `release` (or leaving the ``with`` block) unlinks the file and unlocks it."""

    def __init__(self, fd: int, path: Path) -> None:
        self._fd: int | None = fd
        self.path = path

    def release(self) -> None:
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            self.path.unlink()
        os.close(self._fd)  # closing the last descriptor drops the flock
        self._fd = None

    def __enter__(self) -> RunLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def acquire(directory: Path, key: str) -> RunLock:
    """Locks `directory` (an existing one) for this process; raises `ConfigError` naming the holder.

    ``key`` is the setting the refusal names (``run_dir`` or ``resume``). A lock left by a
    process that is gone is taken over, and said so in one line; a directory where the lock
    file cannot be made is refused too.
    """
    path = Path(directory) / LOCK
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise ConfigError(
                f"invalid value for {key!r}: {str(directory)!r} cannot be written ({exc.strerror}) "
                "(allowed: a directory this process can write in)"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = _read_pid(fd)
            os.close(fd)
            raise _in_use(directory, key, pid) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:  # the holder unlinked it between our open and our flock
            same = False
        if same:
            break
        os.close(fd)
    stale = _read_pid(fd) if os.fstat(fd).st_size else None  # a holder unlinks its file on release
    if stale is not None:
        print(
            f"{PREFIX} {path}: a stale lock of process {stale}, which ended without releasing it, taken over"
        )
    os.ftruncate(fd, 0)
    os.lseek(fd, 0, os.SEEK_SET)
    os.write(fd, f"{os.getpid()}\n".encode())
    return RunLock(fd, path)


def holder(directory: Path) -> str | None:
    """The PID (as text) of the live process that holds `directory`'s lock, or None.

    Creates nothing: a directory without a lock file, or with a stale one, has no holder.
    """
    path = Path(directory) / LOCK
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return _read_pid(fd)
    finally:
        os.close(fd)
    return None


def refuse_if_held(directory: Path, key: str) -> None:
    """Raises `ConfigError` naming the PID when a live process holds `directory`'s lock."""
    pid = holder(directory)
    if pid is not None:
        raise _in_use(directory, key, pid)


def read_metrics(path: Path) -> list[dict[str, Any]]:
    """Rows of a ``metrics.jsonl``; a partial last line (killed mid-write) is dropped."""
    rows = []
    if not Path(path).is_file():
        return rows
    for line in Path(path).read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return rows


def truncate_metrics(path: Path, iteration: int) -> None:
    """Keeps the rows up to `iteration` (atomically): a resumed run rewrites the rest."""
    rows = [r for r in read_metrics(path) if r["iteration"] <= iteration]
    atomic_write(Path(path), "".join(json.dumps(r) + "\n" for r in rows).encode())


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


def package_versions() -> dict[str, str]:
    """Python, platform and the versions of the packages a run's numbers depend on, and the
    project's commit and the CPU (`provenance`)."""
    versions = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in VERSIONED_PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = "not installed"
    try:
        import jax  # lazy: this module loads without JAX (--help, bad input, dry runs)

        versions["jax_backend"] = jax.default_backend()
    except Exception:  # noqa: BLE001 - best effort: versions.json must not stop a run
        pass
    versions.update(provenance())
    return versions


def record_versions(run_dir: Path, resumed_at: int | None) -> None:
    """Writes ``versions.json``; on resume, a ``versions-resumed-N.json`` beside it if they changed
    (the platform string aside; a field the stored file lacks, such as the provenance of a run
    recorded before it was kept, is not a change)."""
    versions = package_versions()
    if resumed_at is None:
        atomic_write(run_dir / VERSIONS, json.dumps(versions, indent=2).encode())
        return
    stored = json.loads((run_dir / VERSIONS).read_text()) if (run_dir / VERSIONS).exists() else {}
    # A versions.json written before the provenance fields existed does not count them as changed.
    changed = [k for k, v in versions.items() if k != "platform" and stored.get(k, v) != v]
    changed += [k for k in stored if k != "platform" and k not in versions]
    if changed:
        name = f"versions-resumed-{resumed_at}.json"
        atomic_write(run_dir / name, json.dumps(versions, indent=2).encode())
        print(f"{PREFIX} warning: {', '.join(changed)} differ from the run's; see {name}", flush=True)


def _git(root: Path, *args: str) -> str | None:
    try:
        out = subprocess.run(
            ["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def git_state(root: Path = PROJECT_ROOT) -> dict[str, Any]:
    """``git_commit`` and ``git_dirty`` of the checkout at `root`; nulls if `root` is not one.

    A checkout that merely encloses `root` (a virtualenv inside another project) is not
    the project's: its top level must be `root` itself.
    """
    none = {"git_commit": None, "git_dirty": None}
    top = _git(root, "rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != Path(root).resolve():
        return none
    commit = _git(root, "rev-parse", "HEAD")
    code_only = ("--", ".", f":(exclude){RESULTS_DATA}")
    status = _git(root, "status", "--porcelain", "--untracked-files=no", *code_only)
    if commit is None or status is None:
        return none
    return {"git_commit": commit, "git_dirty": bool(status)}


def xla_cpu_isa(host_level: str | None, xla_flags: str) -> str | None:
    """The vector extension XLA's CPU compiler targets: the host's widest (`VECTOR_LEVELS`, as
    XLA names it: ``AVX512``, ``AVX2``, ``AVX``, ``SSE4_2``), lowered to ``--xla_cpu_max_isa``
    when `xla_flags` caps it below (an ``AVX512_*`` cap counts as ``AVX512``)."""
    host = XLA_ISA.get(host_level or "")
    cap = None
    for flag in xla_flags.split():
        name, _, value = flag.partition("=")
        if name == "--xla_cpu_max_isa":
            cap = value.upper()
    if cap is None or host is None:
        return host
    cap = "AVX512" if cap.startswith("AVX512") or cap == "AMX" else cap
    if cap not in ISA_ORDER:
        return f"{host} (--xla_cpu_max_isa={cap})"
    return min(host, cap, key=ISA_ORDER.index)


def cpu_info(cpuinfo: Path = Path("/proc/cpuinfo")) -> dict[str, Any]:
    """The processor's name, identity and vector extensions from `cpuinfo` (Linux; else the
    name `platform` gives and nulls), and the extension XLA compiles for under this
    process's ``XLA_FLAGS``: the fields of the module docstring."""
    fields: dict[str, str] = {}
    flags: set[str] = set()
    try:
        for line in cpuinfo.read_text(errors="replace").splitlines():
            name, _, value = line.partition(":")
            name = name.strip()
            if name == "flags" and not flags:
                flags = set(value.split())
            elif name in CPUINFO_FIELDS and name not in fields:
                fields[name] = value.strip()
    except OSError:
        pass

    def number(name: str) -> int | None:
        value = fields.get(name, "")
        return int(value) if value.isdigit() else None

    level = next((lvl for lvl in VECTOR_LEVELS if lvl in flags), None)
    xla_flags = " ".join(os.environ.get("XLA_FLAGS", "").split())
    return {
        "cpu_model": fields.get("model name") or platform.processor() or None,
        "cpu_vendor": fields.get("vendor_id"),
        "cpu_family": number("cpu family"),
        "cpu_model_number": number("model"),
        "cpu_stepping": number("stepping"),
        "cpu_vector_isa": level,
        "xla_cpu_isa": xla_cpu_isa(level, xla_flags),
        "xla_flags": xla_flags,
    }


def provenance() -> dict[str, Any]:
    """The four fields of the module docstring."""
    return {**git_state(), **cpu_info()}
