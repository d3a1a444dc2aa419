"""``executor=ray``: a study's cells as Ray tasks, spread over a Ray cluster's machines.

Each cell's sweep runs as one Ray task (`run_cell`: the cell's sweep command as a subprocess
of the Ray worker, in the study's folder, its output appended to the cell's ``run.log``),
reserving ``ray.cpus_per_cell`` CPUs (default 1); the study keeps as many running as the
cluster has room for (``workers=``, else its CPUs over ``ray.cpus_per_cell``). The sweeps write
straight into the study's folder, so that folder (and this checkout, and the Python
environment at the same path) must be on a filesystem every node sees (NFS or the like).

A cell whose Ray worker or node dies mid-way (`LOST`: the worker crashed, its node died, Ray's
memory monitor killed it) is started again, up to `RESTARTS` times, once its sweep is gone (on
the same machine by its pid, on another while it holds its folder's lock,
`coherent_jax.study.cell.running_pid`), with the command derived again at that time
(`coherent_jax.study.cell.sweep_command`): a resume from its checkpoint, which redoes at most
the iterations after it and duplicates no row. A sweep that exits non-zero by itself (bad
input, divergence) is reported with its exit status and not retried, as the local executor
does. Ctrl-C cancels the tasks (their sweeps get SIGTERM: they checkpoint and stop); a study
killed outright ends its tasks too (Ray ends a dead driver's workers and their processes), each
cell resuming from its last checkpoint when the same command runs again. Ray is optional
(``pip install -e ".[ray]"``) and imported only here, when a study asks for it.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from coherent_jax.study import cell as study_cell
from coherent_jax.study.cell import PACKAGE_ROOT, StudyError
from coherent_jax.study.execute import WITH_PARENT, Job

INSTALL = 'pip install -e ".[ray]"'
RESTARTS = 3  # restarts of one cell whose Ray task was lost
# Ray's errors for a task whose worker process or node went away (not the sweep's own failure).
LOST = ("WorkerCrashedError", "NodeDiedError", "LocalRayletDiedError", "OutOfMemoryError", "ObjectLostError")
# The driver's variables a sweep gets on whichever node it runs: those that change what it
# computes or how fast (JAX's, XLA's, the thread pools', the project's own).
SWEEP_ENV = ("JAX_", "XLA_", "COHERENT_", "OPENBLAS_", "OMP_", "MKL_", "TF_")
CONNECT_TIMEOUT_S = 10.0  # how long a HOST:PORT may take to answer
STOP_WAIT_S = 120.0  # how long `stop` waits for the cancelled sweeps to checkpoint
ADDRESSES = "auto (a cluster started on this machine, or RAY_ADDRESS), HOST:PORT (its head), or local"


def parse_address(text: str) -> str:
    """``ray.address``: ``auto``, ``local`` or ``HOST:PORT``; `ValueError` otherwise."""
    if text in ("auto", "local"):
        return text
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(text)
    return text


def import_ray() -> Any:
    """The ``ray`` module; `StudyError` (one line, exit 2) naming the install command without it."""
    try:
        import ray  # optional dependency, only for executor=ray
    except ImportError:
        raise StudyError(
            f"invalid value for 'executor': 'ray' needs the ray package, which is not installed "
            f"(allowed: local; or install it: {INSTALL})"
        ) from None
    return ray


def connect(address: str) -> Any:
    """The ``ray`` module, connected to the cluster at `address` (``local``: one of its own on
    this machine); `StudyError` when no cluster answers there. A ``HOST:PORT`` is probed first:
    Ray itself would retry an address where nothing listens for minutes."""
    ray = import_ray()
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # `run_cell` needs no package
    options: dict[str, Any] = {"log_to_driver": False, "logging_level": logging.WARNING}
    try:
        if address == "local":
            ray.init(include_dashboard=False, **options)
            return ray
        if address != "auto":
            host, _, port = address.rpartition(":")
            socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT_S).close()
        ray.init(address=address, **options)
    except (OSError, RuntimeError, ValueError) as exc:  # ConnectionError and timeouts are OSErrors
        cause = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise StudyError(
            f"invalid value for 'ray.address': {address!r}: no Ray cluster answers there ({cause}) "
            f"(allowed: {ADDRESSES})"
        ) from None
    return ray


def run_cell(command: list[str], cwd: str, log: str, pid_file: str, env: dict[str, str], root: str) -> int:
    """The Ray task of one cell: its sweep as a subprocess of this worker, to its exit status.

    Runs on any node, so it uses nothing but the standard library (it is sent by value, the
    node need not import this package). The sweep ends with this worker, however that ends
    (`coherent_jax.study.execute.WITH_PARENT`: SIGTERM, on which it checkpoints), and a
    cancelled task (``ray.cancel``, a KeyboardInterrupt here) sends it SIGTERM and waits for it.
    The pid file names the sweep and this machine."""
    sweep_env = dict(os.environ, **env)
    sweep_env["PYTHONPATH"] = root + os.pathsep + os.environ.get("PYTHONPATH", "")
    with open(log, "a") as out:
        proc = subprocess.Popen(
            [sys.executable, "-c", WITH_PARENT, str(os.getpid()), *command],
            stdout=out, stderr=subprocess.STDOUT, cwd=cwd, env=sweep_env,
        )  # fmt: skip
    with open(pid_file, "w") as f:
        f.write(f"{proc.pid} {socket.gethostname()}\n")
    try:
        while proc.poll() is None:
            time.sleep(0.5)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.wait()
    return proc.returncode


def _study_dir(job: Job) -> Path:
    """The study's folder, from a job's log (``STUDY/TASK/ALGO/LABEL/run.log``)."""
    return job.log.parents[len(job.cell.name.split("/"))]


class RayExecutor:
    """Each cell's sweep a Ray task on the cluster at ``address``, ``slots`` at a time."""

    def __init__(self, address: str, cpus_per_cell: float, workers: int = 0, say: Callable | None = None):
        self.ray = ray = connect(address)
        cpus = ray.cluster_resources().get("CPU", 1.0)
        self.slots = workers or max(1, int(cpus // cpus_per_cell))
        self.task = ray.remote(num_cpus=cpus_per_cell, max_retries=0)(run_cell)
        self.env = {k: v for k, v in os.environ.items() if k.startswith(SWEEP_ENV)}
        self.say = say or (lambda line: print(line, flush=True))
        self.running: dict[Any, tuple[Job, int]] = {}  # task -> (job, restarts so far)
        self.lost: list[tuple[Job, int]] = []  # cells to start again once their sweep is gone

    def start(self, job: Job, restarts: int = 0) -> None:
        ref = self.task.remote(
            list(job.command), str(job.cwd), str(job.log), str(job.pid_file), self.env, str(PACKAGE_ROOT)
        )
        self.running[ref] = (job, restarts)

    def wait(self, timeout: float) -> list[tuple[Job, int]]:
        deadline = time.monotonic() + timeout
        ended: list[tuple[Job, int]] = []
        while True:
            self._restart_lost()
            for ref in self._ready(max(0.0, min(1.0, deadline - time.monotonic()))):
                job, restarts = self.running.pop(ref)
                code = self._result(ref, job, restarts)
                if code is not None:
                    job.pid_file.unlink(missing_ok=True)
                    ended.append((job, code))
            if ended or not (self.running or self.lost) or time.monotonic() >= deadline:
                return ended

    def stop(self) -> None:
        """Cancels every running task (its sweep gets SIGTERM, checkpoints and stops) and waits."""
        refs = list(self.running)
        for ref in refs:
            self.ray.cancel(ref)
        if refs:
            self.ray.wait(refs, num_returns=len(refs), timeout=STOP_WAIT_S)
        for job, _ in [*self.running.values(), *self.lost]:
            job.pid_file.unlink(missing_ok=True)
        self.running.clear()
        self.lost.clear()

    def close(self) -> None:
        """Disconnects from the cluster (a local one, ``ray.address=local``, ends)."""
        self.ray.shutdown()

    def _ready(self, timeout: float) -> list[Any]:
        """The tasks that ended, waiting at most `timeout` seconds for one."""
        refs = list(self.running)
        if not refs:
            time.sleep(timeout)
            return []
        ready, _ = self.ray.wait(refs, num_returns=1, timeout=timeout)
        if ready:
            ready, _ = self.ray.wait(refs, num_returns=len(refs), timeout=0)
        return ready

    def _result(self, ref: Any, job: Job, restarts: int) -> int | None:
        """The sweep's exit status; None for a lost task that will be started again."""
        try:
            return int(self.ray.get(ref))
        except self.ray.exceptions.RayError as exc:
            lost = any(c.__name__ in LOST for c in type(exc).__mro__)  # or a subclass of one
            cause = (str(exc).strip().splitlines() or [""])[0]
            if lost and restarts < RESTARTS:
                self._note(job, f"its Ray task was lost ({type(exc).__name__}: {cause}); restart "
                           f"{restarts + 1} of {RESTARTS}, from its checkpoint")  # fmt: skip
                self.lost.append((job, restarts + 1))
                return None
            self._note(job, f"its Ray task failed ({type(exc).__name__}: {cause})")
            return 1

    def _restart_lost(self) -> None:
        """Starts again each lost cell whose sweep is gone, with the command of now (a resume)."""
        waiting = []
        for job, restarts in self.lost:
            study_dir = _study_dir(job)
            if study_cell.running_pid(job.cell, study_dir) is not None:
                waiting.append((job, restarts))
                continue
            job.pid_file.unlink(missing_ok=True)
            command = tuple(study_cell.sweep_command(job.cell, study_dir))
            self.start(Job(job.cell, command, job.cwd, job.log, job.pid_file), restarts)
        self.lost = waiting

    def _note(self, job: Job, text: str) -> None:
        """A line in the study's output and in the cell's log."""
        self.say(f"[study] {job.cell.name}: {text}")
        try:
            with open(job.log, "a") as log:
                log.write(f"[study] {time.strftime('%Y-%m-%d %H:%M:%S')}: {text}\n")
        except OSError:
            pass
