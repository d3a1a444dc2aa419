"""The one launch path of ``train`` and ``sweep``: parse, prepare the run directory, drive the
loop, write the summary, return the exit status.

A command (`coherent_jax.run.single.TrainCommand`, `coherent_jax.sweep`'s
`SweepCommand`) says only what is its own, as a `Command`: how its arguments become a
plan, which checks the plan needs, what it writes besides the shared files and how
it runs. The rest happens here, once, in the same order for both:

1. ``--help`` (the values the other items resolve to) or a dry run (``dry_run=true``,
   ``--print-config``: the resolved config printed, nothing written); SIGINT/SIGTERM
   become a stop request (`run_command`);
2. parse the arguments, or read the stored config for ``resume=DIR`` (`prepare`);
   a ``distributed=true`` command hands its work to the supervisor
   (`coherent_jax.run.multihost.supervise`); the devices and the memory are checked;
3. create the run directory (or check a resumed one's checkpoint and rows) and lock
   it (`coherent_jax.run.runlock`); bad input ends here with `EXIT_BAD_INPUT` and
   nothing written; a SAC run within its warm-up is warned of
   (`coherent_jax.config.checks.warmup_warning`);
4. write the config and ``versions.json`` and drive the loop (`execute`);
5. turn the summary into the exit status (`exit_status`).

`run` is steps 2-5 raising the bad input (`BAD_INPUT`) and a divergence, for the Python
API (`coherent_jax.api`); `launch`, the command line's, reports them in one line with
their exit statuses. A run with ``wandb=true`` needs the ``wandb`` package (and, to log
online, credentials): checked in step 2, before anything is written
(`coherent_jax.run.tracking.preflight`); a W&B run that fails to start ends a new run with
its directory removed again.

The summary helpers are the part of the run both commands' bodies share: the timing
fields of a summary, the line that says a stopped run can be resumed. Their loop is
`coherent_jax.run.loop.drive`, imported when a run starts (the launch path itself
imports no JAX: ``--help``, bad input and dry runs go without it).
"""

from __future__ import annotations

import contextlib
import dataclasses
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from coherent_jax import cli
from coherent_jax.config import Config, ConfigError
from coherent_jax.config.checks import warmup_warning
from coherent_jax.envs.quiet import quiet_imports
from coherent_jax.exit_codes import EXIT_BAD_INPUT, EXIT_DIVERGED, EXIT_OK, signal_status
from coherent_jax.run import multihost, rundir, runlock, tracking
from coherent_jax.run.loop_state import Outcome
from coherent_jax.run.runs import (
    METRICS,
    PREFIX,
    Checkpoint,
    CheckpointError,
    prepare_output_dir,
    read_metrics,
    record_versions,
    split_resume,
)
from coherent_jax.run.stop import DivergenceError, StopRequest
from coherent_jax.run.tracking import TrackingError


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

    def outputs(self, run_dir: Path, plan: Any) -> list[Path]:
        """The files and directories holding logged rows (``metrics.jsonl``, ``tb/``), per point."""

    def write_inputs(self, run_dir: Path, plan: Any, resumed: bool) -> None:
        """The config (and a sweep's grid) in the run directory, before ``versions.json``."""

    def dir_line(self, run_dir: Path, plan: Any) -> str:
        """The start-up line naming the run directory."""

    def describe(self, plan: Any) -> str:
        """The plan as YAML, for a dry run: the config ``config.yaml`` would hold (and a sweep's grid)."""

    def run(self, plan: Any, run_dir: Path | None, checkpoint: Checkpoint | None, stop: StopRequest) -> dict:
        """Runs the plan; returns its summary (with ``stopped_by`` and, for a sweep, ``diverged``)."""


HELP_FLAGS = ("-h", "--help", "help")
PRINT_CONFIG = "--print-config"  # the same as dry_run=true
DRY_RUN = cli.Key(
    default=False,
    parse=cli.boolean,
    allowed="true or false",
    help="prints the resolved config and where the run would write, then exits; writes nothing",
)


def run_command(argv: list[str], help_text: Callable[[list[str]], str], cmd: Command) -> int:
    """The entry of ``train`` and ``sweep``.

    ``--help``: `help_text` of the other items (the values they resolve to: ``preset=thesis
    --help`` shows the preset's). ``dry_run=true`` or ``--print-config``: the resolved
    config (`describe`), nothing written. Otherwise `launch` with SIGINT and SIGTERM
    turned into a stop request; a Ctrl-C before the handler took over exits 130 without
    a traceback. Bad input in the first two is one line and exit status 2 as well.
    """
    items = [a for a in argv if a not in HELP_FLAGS]
    if len(items) < len(argv):
        return _print_or_refuse(lambda: help_text(items))
    try:
        items, dry_run = split_dry_run(items)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    if dry_run:
        return _print_or_refuse(lambda: describe(cmd, items))
    with StopRequest() as stop:
        try:
            return launch(cmd, items, stop)
        except KeyboardInterrupt:
            print(f"{PREFIX} interrupted", file=sys.stderr, flush=True)
            return signal_status(signal.SIGINT)


def split_dry_run(argv: list[str]) -> tuple[list[str], bool]:
    """(the items without ``dry_run=`` and ``--print-config``, whether to do a dry run); a bad
    ``dry_run`` value or a second ``dry_run`` is a `ConfigError`."""
    given = [a for a in argv if a == PRINT_CONFIG or a.split("=", 1)[0].strip() == "dry_run"]
    cli.check_unique(given)
    values = [i == PRINT_CONFIG or cli.parse_value("dry_run", cli.split_item(i)[1], DRY_RUN) for i in given]
    return [a for a in argv if a not in given], any(values)


def _print_or_refuse(make_text: Callable[[], str]) -> int:
    """Prints ``make_text()`` and returns 0; bad input is one line on stderr and status 2."""
    try:
        text = make_text()
    except BAD_INPUT as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    print(text, flush=True)
    return EXIT_OK


def describe(cmd: Command, argv: list[str]) -> str:
    """What a dry run prints: the command's resolved plan as YAML (what ``config.yaml`` would
    hold) and a comment naming where the run would write. The input is parsed and checked
    as a run's is (a resume's stored config is read); nothing is created or written, and
    the devices, the memory and the run directory are not checked."""
    resume_dir, rest = split_resume(argv)
    cli.check_unique(argv)
    plan, run_dir = (cmd.parse(argv), None) if resume_dir is None else cmd.resume(resume_dir, rest)
    cfg = cmd.config(plan)
    warn(cfg)
    where = run_dir or (Path(cfg.run_dir) if cfg.run_dir else cmd.default_dir(cfg))
    verb = "continue in" if resume_dir else "write to"
    return f"{cmd.describe(plan).rstrip()}\n# dry run: nothing written; the run would {verb} {where}"


def warn(cfg: Config) -> None:
    """The warnings of a config that runs but probably not as meant, one line each on stderr."""
    warning = warmup_warning(cfg)
    if warning is not None:
        print(warning, file=sys.stderr, flush=True)


# Bad input: reported in one line, exit status 2, nothing written.
BAD_INPUT = (ConfigError, CheckpointError, TrackingError)


@dataclasses.dataclass(frozen=True)
class Launched:
    """How `run` ended: the exit status, the run directory (None where this process writes
    none) and the summary (None when nothing ran: a supervised run, a complete one, a stop
    before the first iteration)."""

    status: int
    run_dir: Path | None
    summary: dict[str, Any] | None


class _Done(Exception):
    """Nothing to run: the status to exit with (a supervised run's, or 0 for a complete one)."""

    def __init__(self, status: int, run_dir: Path | None = None) -> None:
        self.status = status
        self.run_dir = run_dir


def launch(cmd: Command, argv: list[str], stop: StopRequest) -> int:
    """``train``'s and ``sweep``'s body: `run`, with bad input and a divergence as one line
    on stderr and their exit statuses."""
    try:
        return run(cmd, argv, stop).status
    except BAD_INPUT as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    except DivergenceError as exc:  # a single run; a sweep marks its diverged points instead
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return EXIT_DIVERGED


def run(cmd: Command, argv: list[str], stop: StopRequest) -> Launched:
    """Prepares the run of `argv`, then executes it: what the command line and the Python API
    (`coherent_jax.api.learn`) both run.

    Raises one of `BAD_INPUT` (before anything is written, or on restoring a state that
    does not fit) or `DivergenceError` (a single run that diverged).
    """
    resume_dir, _ = split_resume(argv)
    try:
        plan, run_dir, checkpoint, lock, created = prepare(cmd, argv)
    except _Done as done:
        return Launched(done.status, done.run_dir, None)
    warn(cmd.config(plan))  # every input accepted: what runs, but probably not as meant
    try:
        with lock or contextlib.nullcontext():
            summary = execute(cmd, plan, run_dir, resume_dir is not None, checkpoint, stop)
    except TrackingError:  # W&B did not start: a new run leaves nothing behind, a resumed one its rows
        if run_dir is not None and resume_dir is None:
            rundir.discard_new_dir(run_dir, created)
        raise
    status = exit_status(summary) if summary is not None else signal_status(stop.signum)
    return Launched(status, run_dir, summary)


def prepare(cmd: Command, argv: list[str]):
    """(plan, run_dir, checkpoint, lock, created) of the command line `argv`, every input checked.

    Several hosts: every process parses and reads the checkpoint; only process 0
    (the writer) gets a run directory and its lock. ``created`` is the outermost
    directory made for a new run (None: none made; `rundir.first_missing`). Raises
    `_Done` when there is nothing to run here (a supervised run ended, a resumed run
    is already complete).
    """
    resume_dir, rest = split_resume(argv)
    cli.check_unique(argv)
    if resume_dir is None:
        plan, run_dir = cmd.parse(argv), None
    else:
        plan, run_dir = cmd.resume(resume_dir, rest)
    cfg = cmd.config(plan)
    if cfg.wandb:
        tracking.preflight()
    if multihost.needs_supervisor(cfg.distributed):
        raise _Done(multihost.supervise(cmd.module, argv))
    is_writer = cmd.check(plan)
    if resume_dir is None:
        if not is_writer:
            return plan, None, None, None, None
        path = Path(cfg.run_dir) if cfg.run_dir else cmd.default_dir(cfg)
        runlock.refuse_if_held(path, "run_dir")
        created = rundir.first_missing(path)
        run_dir = prepare_output_dir(path)
        return plan, run_dir, None, runlock.acquire(run_dir, "run_dir"), created
    checkpoint = cmd.resume_point(run_dir, plan)
    if checkpoint is not None:
        finished = checkpoint.iteration >= cfg.num_iterations and (run_dir / cmd.summary_file).exists()
        cmd.check_rows(run_dir, plan, checkpoint, finished)
        if finished:
            print(f"{PREFIX} {run_dir} is already complete ({checkpoint.iteration} iterations)")
            raise _Done(EXIT_OK, run_dir)
    run_dir = run_dir if is_writer else None
    return plan, run_dir, checkpoint, runlock.acquire(run_dir, "resume") if run_dir else None, None


def execute(
    cmd: Command,
    plan: Any,
    run_dir: Path | None,
    resumed: bool,
    checkpoint: Checkpoint | None,
    stop: StopRequest,
) -> dict[str, Any] | None:
    """Writes the run's config and versions and runs it (the input checked); returns its summary,
    None when a signal came before training started."""
    if run_dir and resumed and checkpoint is None:
        start_over(cmd, plan, run_dir)
    if run_dir:
        cmd.write_inputs(run_dir, plan, resumed)
        record_versions(run_dir, None if not resumed else (checkpoint.iteration if checkpoint else 0))
        print(f"{PREFIX} {cmd.dir_line(run_dir, plan)}", flush=True)
    if stop.signum is not None:
        print(f"{PREFIX} stopped by {stop.name} before training started", flush=True)
        return None
    quiet_imports()
    return cmd.run(plan, run_dir, checkpoint, stop)


def start_over(cmd: Command, plan: Any, run_dir: Path) -> None:
    """A resume that found no checkpoint (a run stopped before its first) starts from iteration 0:
    says so in one line on stderr, and sets the rows logged before aside
    (`rundir.set_aside`) rather than overwriting them."""
    outputs = cmd.outputs(run_dir, plan)
    rows = sum(len(read_metrics(p)) for p in outputs if p.name == METRICS)
    n, moved = rundir.set_aside(outputs if rows else [])
    kept = f"; the {rows} rows logged before are set aside as {METRICS}.discarded-{n}" if moved else ""
    print(
        f"{PREFIX} resume found no checkpoint in {run_dir}; starting from iteration 0{kept}",
        file=sys.stderr,
        flush=True,
    )


def exit_status(summary: dict[str, Any]) -> int:
    """The status a finished (or stopped) run exits with: a signal's, a divergence's, or 0."""
    if summary["stopped_by"] is not None:
        return signal_status(signal.Signals[summary["stopped_by"]])
    return EXIT_DIVERGED if summary.get("diverged") else EXIT_OK


def timings(out: Outcome) -> dict[str, float]:
    """The seconds a summary reports: compilation, training, evaluation (this session's compile)."""
    return {
        "compile_s": round(out.compile_s, 2),
        "train_s": round(out.loop.train_s, 2),
        "eval_s": round(out.loop.eval_s, 2),
    }


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
