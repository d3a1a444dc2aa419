"""One process at a time in a run (or sweep) directory: ``DIR/run.lock``.

The process that trains in a directory holds an exclusive ``flock`` on ``DIR/run.lock``,
a file holding its PID, from before it writes anything until it exits; it removes the
file when it is done. A second process, starting or resuming in the same directory, is
refused in one line naming the holder's PID. The kernel drops a ``flock`` when its
holder dies, so the file a SIGKILLed process leaves behind is a stale lock: the next
process takes it over (and writes its own PID into it). A lock file is unlinked
before it is unlocked, and a process that locked a file checks that it is still the
one at ``DIR/run.lock`` (else it retries), so two processes can never both hold the
lock of one directory.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path

from coherent_jax.config import ConfigError

LOCK = "run.lock"


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
    process that is gone is taken over; a directory where the lock file cannot be made is
    refused too.
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
