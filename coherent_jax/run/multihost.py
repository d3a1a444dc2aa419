"""Several processes through `jax.distributed`: start-up, supervision, host copies, agreement.

This module is the part the command line needs before JAX (supervision, the exit of
a worker); the worker's JAX side is `coherent_jax.run.devices`.

``distributed=true`` runs one process per host (or per device group): the same
command everywhere, process 0 being JAX's coordinator and the only one that writes.
This module holds what that needs beyond the device sharding of `coherent_jax.run.devices`:

* **Start-up** (`coherent_jax.run.devices.initialize`): the CPU backend's cross-process collectives are
  switched to gloo (JAX's CPU default has none), the coordinator, process count and
  id come from the cluster (SLURM, Open MPI, ...) or from ``JAX_COORDINATOR_ADDRESS``,
  ``JAX_NUM_PROCESSES``, ``JAX_PROCESS_ID``; the timeouts from `INIT_TIMEOUT_ENV`
  and `HEARTBEAT_TIMEOUT_ENV`.
* **Supervision** (`supervise`): JAX's distributed runtime ends a process whose
  peer died, or whose coordinator cannot be reached, by aborting it from a C++
  thread (SIGABRT and a long native stack trace; jaxlib offers no Python hook).
  So the command line runs the work in a child process and stays as its
  supervisor: it passes the child's own output through, holds back the runtime's
  native log, and when the runtime aborted the child it reports the cause in one
  line and exits with `EXIT_PEER_FAILED`. A failure is therefore never a hang: a
  peer that dies is noticed as soon as its connection closes (about a second), one
  that hangs or loses its network after ``heartbeat`` seconds, an unreachable
  coordinator after ``init`` seconds.
* **Host copies and placement** (`devices.to_host`, `devices.place`): a checkpoint needs the whole
  train state in host memory, although each process holds only its devices' rows
  of the per-env arrays; a restore puts a host copy back as the same global arrays.
* **Agreement** (`devices.largest`, `devices.from_writer`): decisions that change which
  collectives run next (stop now, write a checkpoint) must be the same in every
  process, or one of them would wait for the others forever.
"""

from __future__ import annotations

import collections
import os
import re
import signal
import subprocess
import sys
import threading
import traceback
from collections.abc import Callable, Sequence
from typing import Any

from coherent_jax.config import ConfigError
from coherent_jax.exit_codes import EXIT_PEER_FAILED

# Seconds a process waits for all processes to join the coordinator, and after which
# a peer that stopped sending heartbeats (hung, or its host lost) counts as dead.
INIT_TIMEOUT_ENV = "COHERENT_JAX_INIT_TIMEOUT"
HEARTBEAT_TIMEOUT_ENV = "COHERENT_JAX_HEARTBEAT_TIMEOUT"
DEFAULT_INIT_TIMEOUT_S = 120
DEFAULT_HEARTBEAT_TIMEOUT_S = 30
# Set by the supervisor in its child: the file descriptor of the terminal's stderr,
# for the child's own messages (its fd 2 carries the runtime's native log).
WORKER_ENV = "COHERENT_JAX_WORKER_STDERR"
# The line a worker writes to the runtime log before leaving on a failed collective.
_COLLECTIVE_FAILED = "coherent_jax: collective failed: "
# A line of the runtime's native (glog / absl) log: severity, date, time, thread, file:line.
_NATIVE_LOG = re.compile(r"^[IWEF]\d{4} \d\d:\d\d:\d\d\.\d+\s+\d+\s+\S+:\d+\]")
# Messages of a failed collective or coordination call (a peer closed its connection).
_PEER_FAILURE = re.compile(r"gloo|connection closed by peer|connection reset by peer|socket closed", re.I)


def _timeout(name: str, default: int) -> int:
    """A positive whole number of seconds from the environment variable `name`, else `default`."""
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    if not text.isdigit() or int(text) < 1:
        raise ConfigError(f"invalid value for {name}: {text!r} (allowed: a whole number of seconds >= 1)")
    return int(text)


def _process_label() -> str:
    """``process I of N`` as the environment tells it (before JAX is initialised)."""
    rank = os.environ.get("JAX_PROCESS_ID") or os.environ.get("SLURM_PROCID") or "?"
    size = os.environ.get("JAX_NUM_PROCESSES") or os.environ.get("SLURM_NTASKS") or "?"
    return f"process {rank} of {size}"


# --- supervision (parent side: never initialises a JAX backend) ------------------------------


def is_worker() -> bool:
    """Whether this process runs under `supervise` (it does the work; its parent reports)."""
    return WORKER_ENV in os.environ


def needs_supervisor(enabled: bool) -> bool:
    """Whether a command line with ``distributed=enabled`` should hand its work to `supervise`."""
    return enabled and not is_worker()


class _NativeLog:
    """Filters the runtime's native log: passes other lines on, holds the log's entries back.

    An entry is a native-log line and the lines that continue it (multi-line
    messages, the stack trace of a fatal error). Held entries are written out at
    the end unless the runtime aborted the process; then `summary` replaces them.
    """

    def __init__(self, out: Any) -> None:
        self.out = out
        self.held: collections.deque[str] = collections.deque(maxlen=4000)
        self.in_entry = False
        self.fatal = False
        self.collective: str | None = None

    def feed(self, line: str) -> None:
        if line.startswith(_COLLECTIVE_FAILED):
            self.collective = line[len(_COLLECTIVE_FAILED) :].strip()
            return
        if _NATIVE_LOG.match(line):
            self.in_entry = True
            self.fatal = self.fatal or line.startswith("F")
        if self.in_entry:
            self.held.append(line)
        else:
            self.out.write(line)
            self.out.flush()

    def release(self) -> None:
        """Writes the held entries (a run that ended without the runtime aborting it)."""
        self.out.writelines(self.held)
        self.out.flush()
        self.held.clear()

    def summary(self) -> str:
        """One line: why the runtime stopped this process."""
        text = "".join(self.held)
        if not self.collective and ("RegisterTask" in text or "Connect()" in text):
            address = os.environ.get("JAX_COORDINATOR_ADDRESS", "the cluster's")
            return (
                f"error: {_process_label()}: could not join the coordinator ({address}) within "
                f"{_timeout(INIT_TIMEOUT_ENV, DEFAULT_INIT_TIMEOUT_S)} s (are all processes started, "
                "with the same coordinator address and process count?)"
            )
        dead = re.search(r"tasks are unhealthy[^\n]*\n\s*([\d, ]+)", text)
        if self.collective:
            cause = f"a collective with another process failed ({self.collective})"
        elif dead:
            cause = f"process {dead.group(1).strip()} of the run stopped"
        else:
            cause = "another process of the run stopped or the coordinator became unreachable"
        return (
            f"error: {_process_label()}: {cause}; every process stops (resume from the last checkpoint "
            "with the same command on every process)"
        )


def supervise(module: str, argv: Sequence[str]) -> int:
    """Runs ``python -m module argv`` as a worker child and returns the exit status to use.

    The child's stdout and its own stderr messages reach the terminal unchanged; its
    native runtime log goes through `_NativeLog`. SIGINT and SIGTERM are passed on
    to the child (it stops after the current iteration, as a single process does);
    the child runs in its own session so that a terminal's Ctrl-C reaches it only
    through here, not twice, and it leaves by itself when this process is killed.
    """
    own_stderr = os.dup(2)
    read_fd, write_fd = os.pipe()
    env = {**os.environ, WORKER_ENV: str(own_stderr)}
    try:
        child = subprocess.Popen(
            [sys.executable, "-m", module, *argv],
            env=env,
            stderr=write_fd,
            pass_fds=(own_stderr,),
            start_new_session=True,
        )
    finally:
        os.close(write_fd)
        os.close(own_stderr)

    def forward(signum: int, frame: Any) -> None:
        if child.poll() is None:
            child.send_signal(signum)

    previous = {sig: signal.signal(sig, forward) for sig in (signal.SIGINT, signal.SIGTERM)}
    log = _NativeLog(sys.stderr)
    try:
        with os.fdopen(read_fd, "r", errors="replace") as pipe:
            for line in pipe:
                log.feed(line)
        status = child.wait()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if child.poll() is None:
            child.kill()
            child.wait()
    if log.fatal or status == EXIT_PEER_FAILED:
        print(log.summary(), file=sys.stderr, flush=True)
        return EXIT_PEER_FAILED
    log.release()
    if status < 0:  # the child ended by a signal nobody handled (e.g. SIGKILL from outside)
        name = signal.Signals(-status).name
        print(f"error: {_process_label()}: the worker was ended by {name}", file=sys.stderr, flush=True)
        return 128 - status
    return status


def _adopt_terminal_stderr() -> None:
    """In a worker: Python's stderr to the terminal; a thread that leaves if the supervisor dies."""
    fd = int(os.environ[WORKER_ENV])
    sys.stderr = os.fdopen(fd, "w", buffering=1, errors="replace", closefd=False)
    supervisor = os.getppid()

    def watch() -> None:
        # The supervisor's death (SIGKILL, say) must end the work too: its session is its own.
        while os.getppid() == supervisor:
            threading.Event().wait(0.5)
        os._exit(EXIT_PEER_FAILED)

    threading.Thread(target=watch, name="supervisor-watch", daemon=True).start()


def run_cli(main: Callable[[], int]) -> int:
    """Runs a CLI's ``main``; in a multi-process run, leaves without JAX's shutdown barrier on failure.

    At a normal end every process reaches `jax.distributed.shutdown`'s barrier
    together. On a failure the peers may never get there (they wait in a collective
    for this one), so the process leaves at once with `os._exit` after flushing: a
    failed collective (a peer died) as `EXIT_PEER_FAILED`, reported by the
    supervisor in one line; any other exception with its traceback and status 1;
    a bad input or a divergence with the CLI's own status.
    """
    if is_worker():
        _adopt_terminal_stderr()
    try:
        status = main()
    except Exception as exc:  # noqa: BLE001 - every failure must end the process, not wait
        if not _multi_process():
            raise
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        if _PEER_FAILURE.search(str(exc)):
            os.write(2, f"{_COLLECTIVE_FAILED}{first[:300]}\n".encode())
            _leave(EXIT_PEER_FAILED)
        traceback.print_exc()
        _leave(1)
    if status != 0 and _multi_process():
        _leave(status)
    return status


def _multi_process() -> bool:
    # Without JAX imported, `jax.distributed` cannot have been initialised: one process.
    jax = sys.modules.get("jax")
    return jax is not None and jax.distributed.is_initialized() and jax.process_count() > 1


def _leave(status: int) -> None:
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)
