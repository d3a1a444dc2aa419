"""The one launch path of ``train`` and ``sweep``: parse, prepare the run directory, drive the
loop, write the summary, return the exit status.

A command (`coherent_jax.train`'s `TrainCommand`, `coherent_jax.sweep`'s
`SweepCommand`) says only what is its own, as a `Command`: how its arguments become a
plan, which checks the plan needs, what it writes besides the shared files and how
it runs. The rest happens here, once, in the same order for both:

1. ``--help``; SIGINT/SIGTERM become a stop request (`run_command`);
2. parse the arguments, or read the stored config for ``resume=DIR`` (`prepare`);
   a ``distributed=true`` command hands its work to the supervisor
   (`coherent_jax.multihost.supervise`); the devices and the memory are checked;
3. create the run directory (or check a resumed one's checkpoint and rows) and lock
   it (`coherent_jax.runlock`); bad input ends here with `EXIT_BAD_INPUT` and
   nothing written;
4. write the config and ``versions.json`` and drive the loop (`execute`);
5. turn the summary into the exit status (`exit_status`).

`drive` and the summary helpers are the part of the run both commands' bodies share:
the loop under a stop request, the timing fields of a summary, the line that says a
stopped run can be resumed.
"""

from __future__ import annotations

import contextlib
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from coherent_jax import cli, multihost, runlock
from coherent_jax.config import Config, ConfigError
from coherent_jax.divergence import DivergenceError
from coherent_jax.exit_codes import EXIT_BAD_INPUT, EXIT_DIVERGED, EXIT_OK, signal_status
from coherent_jax.loop import PREFIX, StopRequest, run_loop
from coherent_jax.loop_state import Job, Outcome
from coherent_jax.quiet import quiet_imports
from coherent_jax.runs import Checkpoint, CheckpointError, prepare_output_dir, record_versions, split_resume


class Command(Protocol):
    """What a command of the launch path has of its own.

    ``Plan`` is the command's parsed input: a `Config` for a single run, a
    `coherent_jax.sweep.SweepPlan` for a sweep.
    """

    module: str  # ``python -m <module>``, which the supervisor of a distributed run starts
    summary_file: str  # written last: a resumed run holding it (and at its budget) is complete

    def config(self, plan: Any) -> Config:
        """The settings the whole run shares."""

    def parse(self, argv: list[str]) -> Any:
        """The plan of a new run; raises `ConfigError` naming the bad item."""

    def resume(self, resume_dir: str, rest: list[str]) -> tuple[Any, Path]:
        """The plan and the directory of the run in `resume_dir`, with the overrides `rest`."""

    def check(self, plan: Any) -> bool:
        """Devices and memory; returns whether this process writes the outputs."""

    def default_dir(self, cfg: Config) -> Path:
        """Where a run without ``run_dir`` writes."""

    def resume_point(self, run_dir: Path, plan: Any) -> Checkpoint | None:
        """The checkpoint a resume starts from (`runs.resume_point`)."""

    def check_rows(self, run_dir: Path, plan: Any, checkpoint: Checkpoint, finished: bool) -> None:
        """The logged rows up to the checkpoint are whole; raises `ConfigError` otherwise."""

    def write_inputs(self, run_dir: Path, plan: Any, resumed: bool) -> None:
        """The config (and a sweep's grid) in the run directory, before ``versions.json``."""

    def dir_line(self, run_dir: Path, plan: Any) -> str:
        """The start-up line naming the run directory."""

    def run(self, plan: Any, run_dir: Path | None, checkpoint: Checkpoint | None, stop: StopRequest) -> dict:
        """Runs the plan; returns its summary (with ``stopped_by`` and, for a sweep, ``diverged``)."""


def run_command(
    argv: list[str], help_text: Callable[[], str], body: Callable[[list[str], StopRequest], int]
) -> int:
    """The entry of ``train`` and ``sweep``: ``--help``, else ``body(argv, stop)`` with SIGINT
    and SIGTERM turned into a stop request; a Ctrl-C before the handler took over exits
    130 without a traceback."""
    if any(a in ("-h", "--help", "help") for a in argv):
        print(help_text())
        return EXIT_OK
    with StopRequest() as stop:
        try:
            return body(argv, stop)
        except KeyboardInterrupt:
            print(f"{PREFIX} interrupted", file=sys.stderr, flush=True)
            return signal_status(signal.SIGINT)


@contextlib.contextmanager
def _bad_input():
    """Turns a `ConfigError` or `CheckpointError` into the one-line refusal."""
    try:
        yield
    except (ConfigError, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        raise _Refused from None


class _Refused(Exception):
    """Bad input, already reported."""


class _Done(Exception):
    """Nothing to run: the status to exit with (a supervised run's, or 0 for a complete one)."""

    def __init__(self, status: int) -> None:
        self.status = status


def launch(cmd: Command, argv: list[str], stop: StopRequest) -> int:
    """``train``'s and ``sweep``'s body: prepare the run, then execute it; returns the exit status."""
    resume_dir, _ = split_resume(argv)
    try:
        with _bad_input():
            plan, run_dir, checkpoint, lock = prepare(cmd, argv)
    except _Refused:
        return EXIT_BAD_INPUT
    except _Done as done:
        return done.status
    with lock or contextlib.nullcontext():
        return execute(cmd, plan, run_dir, resume_dir is not None, checkpoint, stop)


def prepare(cmd: Command, argv: list[str]):
    """(plan, run_dir, checkpoint, lock) of the command line `argv`, every input checked.

    Several hosts: every process parses and reads the checkpoint; only process 0
    (the writer) gets a run directory and its lock. Raises `_Done` when there is
    nothing to run here (a supervised run ended, a resumed run is already complete).
    """
    resume_dir, rest = split_resume(argv)
    cli.check_unique(argv)
    if resume_dir is None:
        plan, run_dir = cmd.parse(argv), None
    else:
        plan, run_dir = cmd.resume(resume_dir, rest)
    cfg = cmd.config(plan)
    if multihost.needs_supervisor(cfg.distributed):
        raise _Done(multihost.supervise(cmd.module, argv))
    is_writer = cmd.check(plan)
    if resume_dir is None:
        if not is_writer:
            return plan, None, None, None
        path = Path(cfg.run_dir) if cfg.run_dir else cmd.default_dir(cfg)
        runlock.refuse_if_held(path, "run_dir")
        run_dir = prepare_output_dir(path)
        return plan, run_dir, None, runlock.acquire(run_dir, "run_dir")
    checkpoint = cmd.resume_point(run_dir, plan)
    if checkpoint is not None:
        finished = checkpoint.iteration >= cfg.num_iterations and (run_dir / cmd.summary_file).exists()
        cmd.check_rows(run_dir, plan, checkpoint, finished)
        if finished:
            print(f"{PREFIX} {run_dir} is already complete ({checkpoint.iteration} iterations)")
            raise _Done(EXIT_OK)
    run_dir = run_dir if is_writer else None
    return plan, run_dir, checkpoint, runlock.acquire(run_dir, "resume") if run_dir else None


def execute(
    cmd: Command,
    plan: Any,
    run_dir: Path | None,
    resumed: bool,
    checkpoint: Checkpoint | None,
    stop: StopRequest,
) -> int:
    """Writes the run's config and versions, runs it, and returns the exit status (the input checked)."""
    if run_dir:
        cmd.write_inputs(run_dir, plan, resumed)
        record_versions(run_dir, None if not resumed else (checkpoint.iteration if checkpoint else 0))
        print(f"{PREFIX} {cmd.dir_line(run_dir, plan)}", flush=True)
    if stop.signum is not None:
        print(f"{PREFIX} stopped by {stop.name} before training started", flush=True)
        return signal_status(stop.signum)
    quiet_imports()
    try:
        summary = cmd.run(plan, run_dir, checkpoint, stop)
    except CheckpointError as exc:  # a state that does not fit this trainer, found on restoring it
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    except DivergenceError as exc:  # a single run; a sweep marks its diverged points instead
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return EXIT_DIVERGED
    return exit_status(summary)


def exit_status(summary: dict[str, Any]) -> int:
    """The status a finished (or stopped) run exits with: a signal's, a divergence's, or 0."""
    if summary["stopped_by"] is not None:
        return signal_status(signal.Signals[summary["stopped_by"]])
    return EXIT_DIVERGED if summary.get("diverged") else EXIT_OK


def drive(
    job: Job,
    stop: StopRequest | None,
    resume: Checkpoint | None,
    progress_fn: Callable[[int, dict[str, float]], None] | None = None,
) -> Outcome:
    """`run_loop` under `stop`, or under a stop request of its own when called from Python."""
    with contextlib.ExitStack() as stack:
        stop = stop or stack.enter_context(StopRequest())
        return run_loop(job, stop, resume, progress_fn)


def timings(out: Outcome) -> dict[str, float]:
    """The seconds a summary reports: compilation, training, evaluation (this session's compile)."""
    return {
        "compile_s": round(out.compile_s, 2),
        "train_s": round(out.loop.train_s, 2),
        "eval_s": round(out.loop.eval_s, 2),
    }


def platform(out: Outcome) -> dict[str, Any]:
    """Where a summary's run ran: JAX's version, its backend, the devices used."""
    import jax

    return {"jax_version": jax.__version__, "backend": jax.default_backend(), "num_devices": out.num_devices}


def report_stopped(out: Outcome, run_dir: Path | None) -> bool:
    """Whether a signal stopped the run; if so, says where it stopped and how to continue."""
    if out.stopped_by is None:
        return False
    print(
        f"{PREFIX} stopped by {out.stopped_by} after iteration {out.done}; "
        + (f"checkpoint saved; continue with resume={run_dir}" if run_dir else "nothing saved"),
        flush=True,
    )
    return True
