"""A stopped cell's resumable state as one committed file, so that it continues elsewhere.

A cell that does not finish in one stretch of work leaves its sweep directory where it
ran: the checkpoint and the per-seed logs, which git does not keep. A cell longer than
the time a machine is kept could then never finish. `pack` writes what the sweep needs
to continue into ``CELL/carry.tar.gz``, which git keeps:

* the sweep's ``checkpoint.msgpack`` (every point's whole state), ``config.yaml``,
  ``grid.json`` and ``versions*.json``;
* each point's ``config.yaml`` and ``metrics.jsonl`` (its curve so far).

TensorBoard files, locks and ``run.log`` stay behind. `unpack` restores the sweep
directory in a checkout that has the file and no sweep directory; a study (`coherent_jax.study.cell.prepare`)
does so before it resumes the cell, which continues from the checkpoint as any stopped
cell does (a resume on another machine or commit records ``versions-resumed-N.json``).
A finished cell's carry file is dropped when the cell is committed.

The archive is the same bytes for the same files (sorted, no times or owners), so a
cell packed twice unchanged is no new blob. A pack larger than `MAX_BYTES` is refused:
an SAC checkpoint holds its replay buffer (hundreds of MB), and a cell of
``coherent.gradient=episode`` the episode window of every env (28 MB packed for 5 seeds
at the HalfCheetah defaults), so those cells must finish on the machine where they start
(stopped there, they resume from the local checkpoint).
"""

from __future__ import annotations

import gzip
import io
import os
import shutil
import subprocess
import tarfile
from pathlib import Path, PurePosixPath

CARRY = "carry.tar.gz"
SWEEP = "sweep"
SWEEP_PATTERNS = ("checkpoint.msgpack", "config.yaml", "grid.json", "versions*.json")
POINT_PATTERNS = ("config.yaml", "metrics.jsonl")
MAX_BYTES = 16 * 2**20


class CarryError(ValueError):
    """A cell that cannot be packed or a carry file that cannot be unpacked (one line)."""


def carry_path(cell_dir: Path) -> Path:
    return Path(cell_dir) / CARRY


def carried_files(sweep: Path) -> list[Path]:
    """The files of sweep directory `sweep` that a carry file holds, sorted."""
    files = [f for pattern in SWEEP_PATTERNS for f in sweep.glob(pattern)]
    for point in sorted(p for p in sweep.iterdir() if p.is_dir()):
        files += [f for pattern in POINT_PATTERNS for f in point.glob(pattern)]
    return sorted(f for f in files if f.is_file())


def _archive(sweep: Path, files: list[Path]) -> bytes:
    raw = io.BytesIO()
    with gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as gz, tarfile.open(fileobj=gz, mode="w") as tar:
        for f in files:
            data = f.read_bytes()
            info = tarfile.TarInfo(f"{SWEEP}/{f.relative_to(sweep).as_posix()}")
            info.size, info.mode = len(data), 0o644
            tar.addfile(info, io.BytesIO(data))
    return raw.getvalue()


def pack(cell_dir: Path, max_bytes: int = MAX_BYTES) -> Path:
    """Writes ``cell_dir/carry.tar.gz`` from the stopped sweep in ``cell_dir/sweep`` (atomically).

    Raises `CarryError` for a sweep that has finished or has no checkpoint, and for an
    archive over `max_bytes`; the carry file already there is then left as it was.
    """
    sweep = Path(cell_dir) / SWEEP
    if (sweep / "sweep.json").exists():
        raise CarryError(f"cell {str(cell_dir)!r} has finished (allowed: a stopped cell)")
    if not (sweep / "checkpoint.msgpack").is_file():
        raise CarryError(f"cell {str(cell_dir)!r} has no checkpoint to carry (allowed: a stopped cell)")
    files = carried_files(sweep)
    # Checkpoints are float32 arrays, which gzip shrinks little: twice the limit unpacked
    # is refused before the archive is built (an SAC cell's is hundreds of MB).
    raw = sum(f.stat().st_size for f in files)
    data = _archive(sweep, files) if raw <= 2 * max_bytes else None
    if data is None or len(data) > max_bytes:
        size = f"packs to {len(data) / 2**20:.1f} MB" if data else f"holds {raw / 2**20:.0f} MB to pack"
        raise CarryError(
            f"cell {str(cell_dir)!r} {size} "
            f"(allowed: at most {max_bytes / 2**20:.0f} MB; an SAC cell carries its replay buffer, "
            "an episode-gradient cell its episode window)"
        )
    target = carry_path(cell_dir)
    tmp = target.with_name(target.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, target)
    return target


def _members(tar: tarfile.TarFile, path: Path) -> list[tarfile.TarInfo]:
    """The archive's members, each a regular file under ``sweep/`` (else `CarryError`)."""
    members = tar.getmembers()
    for m in members:
        parts = PurePosixPath(m.name).parts
        if not m.isfile() or len(parts) < 2 or parts[0] != SWEEP or ".." in parts or m.name.startswith("/"):
            raise CarryError(
                f"invalid carry file {str(path)!r}: member {m.name!r} (allowed: files under sweep/)"
            )
    return members


def unpack(cell_dir: Path) -> bool:
    """Restores ``cell_dir/sweep`` from the carry file if there is one and no sweep directory.

    Returns whether it did. The directory appears whole or not at all (written beside it,
    then renamed); the carry file stays until the cell is committed finished.
    """
    cell_dir, path = Path(cell_dir), carry_path(cell_dir)
    if (cell_dir / SWEEP).exists() or not path.is_file():
        return False
    staging = cell_dir / f".{SWEEP}.unpacking"
    shutil.rmtree(staging, ignore_errors=True)  # what an unpack stopped halfway left
    try:
        with tarfile.open(path, mode="r:gz") as tar:
            members = _members(tar, path)
            for m in members:
                target = staging / PurePosixPath(m.name).relative_to(SWEEP)
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_bytes(tar.extractfile(m).read())
    except (OSError, tarfile.TarError, EOFError) as exc:
        raise CarryError(f"unreadable carry file {str(path)!r}: {exc}") from None
    os.replace(staging, cell_dir / SWEEP)
    return True


def carried_metrics(cell_dir: Path) -> dict[str, bytes]:
    """Each point's ``metrics.jsonl`` in the carry file, by point name (empty if none)."""
    path = carry_path(cell_dir)
    if not path.is_file():
        return {}
    try:
        with tarfile.open(path, mode="r:gz") as tar:
            return {
                PurePosixPath(m.name).parts[1]: tar.extractfile(m).read()
                for m in _members(tar, path)
                if PurePosixPath(m.name).name == "metrics.jsonl"
            }
    except (OSError, tarfile.TarError, EOFError) as exc:
        raise CarryError(f"unreadable carry file {str(path)!r}: {exc}") from None


def drop(cell_dir: Path, root: Path) -> list[str]:
    """Deletes a finished cell's carry file; returns its path if the git checkout at `root`
    tracks it (a removal to commit), else nothing. A tracked file already deleted (the cell
    finished in a run without ``--commit``) is returned too, so its removal is committed."""
    path = carry_path(cell_dir)
    tracked = subprocess.run(
        ["git", "-C", str(root), "ls-files", "--error-unmatch", "--", str(path)], capture_output=True
    )
    path.unlink(missing_ok=True)
    return [str(path)] if tracked.returncode == 0 else []
