"""The helpers every command's ``main`` shares, in the order it calls them.

``python -m coherent_jax.train`` (`coherent_jax.train.main`, whose run is
`coherent_jax.run.single.launch_train`) and ``python -m coherent_jax.sweep``
(`coherent_jax.sweep.main`, `coherent_jax.sweep.launch_sweep`) each read top down:

1. `split_mode`: ``--help`` (the values the other items resolve to), a dry run
   (``dry_run=true``, ``--print-config``: the resolved config printed, nothing written) or a run;
2. parse the arguments, or read the stored config for ``resume=DIR``; `preflight`: a
   ``wandb=true`` run needs the ``wandb`` package (`coherent_jax.run.tracking.preflight`), a
   ``distributed=true`` command hands its work to the supervisor
   (`coherent_jax.run.multihost.supervise`); the command checks its devices and memory;
3. `hold_new` or, for ``resume=``, `is_complete` then `hold_resumed`: the run directory made
   (or a resumed one's checkpoint and rows checked) and locked (`coherent_jax.run.runlock`);
   `warn` of a config that runs but probably not as meant;
4. under `holding`: `begin` (a resume without a checkpoint starts over), the command writes its
   config, `started` writes ``versions.json`` and says where the run writes; the command builds
   its trainer and drives the loop (`coherent_jax.run.loop.drive`);
5. `exit_status` of the summary.

Bad input anywhere in 1-3 raises one of `REFUSED` before anything is written; ``main`` turns it
into one line and its exit status (`refuse`). The Python API (`coherent_jax.api.learn`) calls
`launch_train` and lets it raise. A W&B run that fails to start ends a new run with its
directory removed again (`holding`).

The summary helpers are also shared: the timing fields of a summary (`timings`), the line that
says a stopped run can be resumed (`report_stopped`). Nothing here imports JAX: ``--help``,
bad input and dry runs go without it.
"""

from __future__ import annotations

import contextlib
import signal
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from coherent_jax.config import Config, ConfigError, cli
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
)
from coherent_jax.run.stop import CALLBACK, DivergenceError, StopRequest
from coherent_jax.run.tracking import TrackingError

HELP_FLAGS = ("-h", "--help", "help")
PRINT_CONFIG = "--print-config"  # the same as dry_run=true
DRY_RUN = cli.Key(
    default=False,
    parse=cli.boolean,
    allowed="true or false",
    help="prints the resolved config and where the run would write, then exits; writes nothing",
)
HELP, DRY, RUN = "help", "dry_run", "run"

# Bad input: reported in one line, exit status 2, nothing written.
BAD_INPUT = (ConfigError, CheckpointError, TrackingError)
# What ends a command with one line on stderr: bad input, and a single run's divergence.
REFUSED = (*BAD_INPUT, DivergenceError)


class Launched(NamedTuple):
    """How a command's run ended: the exit status, the run directory (None where this process
    writes none) and the summary (None when nothing ran: a supervised run, a complete one, a
    stop before the first iteration)."""

    status: int
    run_dir: Path | None
    summary: dict[str, Any] | None


class Held(NamedTuple):
    """A run directory ready to write to: ``run_dir`` None where this process writes nothing
    (a second host); ``checkpoint`` the one a resume starts from; ``lock`` held on it;
    ``created`` the outermost directory made for a new run (`rundir.first_missing`)."""

    run_dir: Path | None
    resumed: bool
    checkpoint: Checkpoint | None = None
    lock: runlock.RunLock | None = None
    created: Path | None = None


def split_mode(argv: Sequence[str]) -> tuple[str, list[str]]:
    """(`HELP`, `DRY` or `RUN`, the other items). A bad ``dry_run`` value or a second ``dry_run``
    is a `ConfigError`."""
    items = [a for a in argv if a not in HELP_FLAGS]
    if len(items) < len(argv):
        return HELP, items
    given = [a for a in items if a == PRINT_CONFIG or a.split("=", 1)[0].strip() == "dry_run"]
    cli.check_unique(given)
    dry = any(i == PRINT_CONFIG or cli.parse_value("dry_run", cli.split_item(i)[1], DRY_RUN) for i in given)
    return (DRY if dry else RUN), [a for a in items if a not in given]


def answer(text: str) -> int:
    """Prints a help or dry-run text; exit status 0."""
    print(text, flush=True)
    return EXIT_OK


def refuse(exc: Exception) -> int:
    """One of `REFUSED` as one line on stderr; its exit status (2 bad input, 3 diverged)."""
    print(f"error: {exc}", file=sys.stderr, flush=True)
    return EXIT_DIVERGED if isinstance(exc, DivergenceError) else EXIT_BAD_INPUT


def interrupted() -> int:
    """A Ctrl-C before the stop request took over: one line, no traceback, SIGINT's status."""
    print(f"{PREFIX} interrupted", file=sys.stderr, flush=True)
    return signal_status(signal.SIGINT)


def where(cfg: Config, run_dir: Path | None, default: Path, resumed: bool) -> str:
    """A dry run's last line: nothing written, and where the run would write."""
    verb = "continue in" if resumed else "write to"
    return f"# dry run: nothing written; the run would {verb} {run_dir or Path(cfg.run_dir or default)}"


def warn(cfg: Config) -> None:
    """The warnings of a config that runs but probably not as meant, one line each on stderr."""
    warning = warmup_warning(cfg)
    if warning is not None:
        print(warning, file=sys.stderr, flush=True)


def preflight(cfg: Config, module: str, argv: Sequence[str]) -> int | None:
    """Checks before the devices: W&B importable with ``wandb=true``. With ``distributed=true``
    on the first process, runs the supervisor of ``python -m module argv`` and returns its exit
    status; None: this process runs the command itself."""
    if cfg.wandb:
        tracking.preflight()
    if multihost.needs_supervisor(cfg.distributed):
        return multihost.supervise(module, list(argv))
    return None


def hold_new(path: Path, is_writer: bool) -> Held:
    """A new run's directory `path` made and locked (refused while another process holds it);
    nothing for a process that does not write."""
    if not is_writer:
        return Held(None, resumed=False)
    runlock.refuse_if_held(path, "run_dir")
    created = rundir.first_missing(path)
    run_dir = prepare_output_dir(path)
    return Held(run_dir, False, None, runlock.acquire(run_dir, "run_dir"), created)


def is_complete(run_dir: Path, checkpoint: Checkpoint | None, cfg: Config, summary_file: str) -> bool:
    """Whether a resumed run is done: its checkpoint at the budget and its summary written."""
    return (
        checkpoint is not None
        and checkpoint.iteration >= cfg.num_iterations
        and (run_dir / summary_file).exists()
    )


def complete(run_dir: Path, checkpoint: Checkpoint) -> Launched:
    """A resume of a complete run: says so; nothing runs, exit status 0."""
    print(f"{PREFIX} {run_dir} is already complete ({checkpoint.iteration} iterations)")
    return Launched(EXIT_OK, run_dir, None)


def hold_resumed(run_dir: Path, checkpoint: Checkpoint | None, is_writer: bool) -> Held:
    """A resumed run's directory locked (refused while another process holds it)."""
    if not is_writer:
        return Held(None, True, checkpoint)
    return Held(run_dir, True, checkpoint, runlock.acquire(run_dir, "resume"))


@contextlib.contextmanager
def holding(held: Held) -> Iterator[Held]:
    """`held`'s lock for the run's length; a W&B run that does not start (`TrackingError`)
    leaves nothing behind a new run (its directory removed again), a resumed one its rows."""
    with held.lock or contextlib.nullcontext():
        try:
            yield held
        except TrackingError:
            if held.run_dir is not None and not held.resumed:
                rundir.discard_new_dir(held.run_dir, held.created)
            raise


def begin(held: Held, outputs: list[Path]) -> None:
    """Before the command writes its config: a resume that found no checkpoint (a run stopped
    before its first) starts from iteration 0, says so in one line on stderr, and sets the rows
    of `outputs` logged before aside (`rundir.set_aside`) rather than overwriting them."""
    if not (held.run_dir and held.resumed and held.checkpoint is None):
        return
    rows = sum(len(read_metrics(p)) for p in outputs if p.name == METRICS)
    n, moved = rundir.set_aside(outputs if rows else [])
    kept = f"; the {rows} rows logged before are set aside as {METRICS}.discarded-{n}" if moved else ""
    print(
        f"{PREFIX} resume found no checkpoint in {held.run_dir}; starting from iteration 0{kept}",
        file=sys.stderr,
        flush=True,
    )


def started(held: Held, line: str, stop: StopRequest) -> bool:
    """After the command wrote its config: ``versions.json`` and the line naming the run
    directory (`line`). Returns whether to train: False (said in one line) when a signal came
    before training started."""
    if held.run_dir:
        record_versions(
            held.run_dir, None if not held.resumed else (held.checkpoint.iteration if held.checkpoint else 0)
        )
        print(f"{PREFIX} {line}", flush=True)
    if stop.signum is not None:
        print(f"{PREFIX} stopped by {stop.name} before training started", flush=True)
        return False
    quiet_imports()
    return True


def exit_status(summary: dict[str, Any] | None, stop: StopRequest) -> int:
    """The status a run exits with: a signal's (also one before training: no summary), a
    divergence's, or 0 (also for a stop a callback asked for: the user's own request)."""
    if summary is None:
        return signal_status(stop.signum)
    if summary["stopped_by"] not in (None, CALLBACK):
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
    """Whether a signal or a callback stopped the run; if so, says where it stopped and how to
    continue."""
    if out.stopped_by is None:
        return False
    why = f" ({out.stop_reason})" if out.stop_reason else ""
    print(
        f"{PREFIX} stopped by {out.stopped_by}{why} after iteration {out.done}; "
        + (f"checkpoint saved; continue with resume={run_dir}" if run_dir else "nothing saved"),
        flush=True,
    )
    return True
