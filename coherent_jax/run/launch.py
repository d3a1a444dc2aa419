"""The launch path of ``python -m coherent_jax.train`` and ``python -m coherent_jax.sweep``, from
the command line to the exit status, top down.

`coherent_jax.train.main` and `coherent_jax.sweep.main` first call `split_mode`: ``--help``
(the values the other items resolve to), a dry run (``dry_run=true``, ``--print-config``:
`describe_train`, `describe_sweep` print the resolved config, nothing written) or a run,
`launch_train` (also what the Python API's `coherent_jax.api.learn` runs) or `launch_sweep`.
Each of these reads top down:

1. parse the arguments, or read the stored config for ``resume=DIR`` (`read_train_config`,
   `coherent_jax.run.sweep.read_sweep`);
2. `preflight`: a ``wandb=true`` run needs the ``wandb`` package
   (`coherent_jax.run.outputs.wandb_preflight`), a ``distributed=true`` command hands its work
   to the supervisor (`coherent_jax.run.multihost.supervise`); then the devices and the memory
   (`coherent_jax.run.training.check_train`, `coherent_jax.run.training.check_sweep`: JAX from
   here on);
3. `lock_new_dir` or, for ``resume=``, `is_complete` then `lock_resumed_dir`: the directory
   made (or a resumed one's checkpoint and rows checked) and locked
   (`coherent_jax.run.rundir.acquire`), a `HeldDir`; `warn` of a config that runs but probably
   not as meant;
4. while `locked`: `restart_if_no_checkpoint` (a resume without a checkpoint starts over), the
   config written (`write_run_config`, `write_grid`), `record_start` (``versions.json`` and
   the line saying where the run writes), then the run itself
   (`coherent_jax.run.training.train`, `coherent_jax.run.training.run_sweep`);
5. `exit_status` of the summary.

Bad input anywhere in 1-3 raises one of `REFUSED` before anything is written; ``main`` turns it
into one line and its exit status (`refuse`). The Python API calls `launch_train` and lets it
raise. A W&B run that fails to start ends a new run with its directory removed again
(`locked`). Nothing here imports JAX: ``--help``, bad input and dry runs go without it; a run
imports `coherent_jax.run.training` once its input is parsed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import signal
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import yaml

from coherent_jax.config import Config, ConfigError, cli, parse_overrides
from coherent_jax.config.checks import warmup_warning
from coherent_jax.envs.quiet import quiet_imports
from coherent_jax.envs.registry import task_label
from coherent_jax.exit_codes import EXIT_BAD_INPUT, EXIT_DIVERGED, EXIT_ENV_FAILED, EXIT_OK, signal_status
from coherent_jax.run import multihost, rundir, sweep
from coherent_jax.run.checkpoint import (
    Checkpoint,
    CheckpointError,
    config_text,
    load_config,
    resume_config,
    resume_point,
    split_resume,
    write_config,
)
from coherent_jax.run.loop_state import CALLBACK, DivergenceError, EnvError, StopRequest
from coherent_jax.run.outputs import Callback, TrackingError, wandb_preflight
from coherent_jax.run.rundir import (
    METRICS,
    PREFIX,
    atomic_write,
    prepare_output_dir,
    read_metrics,
    record_versions,
)
from coherent_jax.run.sweep import SweepPlan, read_sweep

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
# What ends a command with one line on stderr: bad input, a single run's divergence, and a
# task's own env raising mid-run.
REFUSED = (*BAD_INPUT, DivergenceError, EnvError)
TRAIN_MODULE = "coherent_jax.train"  # ``python -m MODULE``, which the supervisor of a distributed run starts
SWEEP_MODULE = "coherent_jax.sweep"  # the same for a sweep
RUN_SUMMARY = "summary.json"  # written last: a resumed run holding it (and at its budget) is complete
SWEEP_SUMMARY = "sweep.json"  # written last: a resumed sweep holding it (and at its budget) is complete


class Launched(NamedTuple):
    """How a command's run ended: the exit status, the run directory (None where this process
    writes none) and the summary (None when nothing ran: a supervised run, a complete one, a
    stop before the first iteration)."""

    status: int
    run_dir: Path | None
    summary: dict[str, Any] | None


class HeldDir(NamedTuple):
    """A run directory ready to write to: ``run_dir`` None where this process writes nothing
    (a second host); ``checkpoint`` the one a resume starts from; ``lock`` held on it;
    ``created`` the outermost directory made for a new run (`rundir.first_missing`)."""

    run_dir: Path | None
    resumed: bool
    checkpoint: Checkpoint | None = None
    lock: rundir.RunLock | None = None
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


def print_answer(text: str) -> int:
    """Prints a help or dry-run text; exit status 0."""
    print(text, flush=True)
    return EXIT_OK


def refuse(exc: Exception) -> int:
    """One of `REFUSED` as one line on stderr; its exit status (2 bad input, 3 diverged, 1 an env
    raised)."""
    print(f"error: {exc}", file=sys.stderr, flush=True)
    if isinstance(exc, EnvError):
        return EXIT_ENV_FAILED
    return EXIT_DIVERGED if isinstance(exc, DivergenceError) else EXIT_BAD_INPUT


def interrupted() -> int:
    """A Ctrl-C before the stop request took over: one line, no traceback, SIGINT's status."""
    print(f"{PREFIX} interrupted", file=sys.stderr, flush=True)
    return signal_status(signal.SIGINT)


def launch_train(argv: Sequence[str], stop: StopRequest, callbacks: Sequence[Callback] = ()) -> Launched:
    """Runs the command line `argv` of ``python -m coherent_jax.train``: parse, check, prepare
    the run directory, train (with `callbacks`, from the Python API), exit status.

    Raises one of `REFUSED` (bad input before anything is written, or on restoring a
    state that does not fit; a divergence).
    """
    cfg, resume_dir = read_train_config(argv)
    supervised = preflight(cfg, TRAIN_MODULE, argv)
    if supervised is not None:
        return Launched(supervised, None, None)
    from coherent_jax.run.training import check_train, train  # lazy: JAX; bad input goes without

    is_writer = check_train(cfg)
    if resume_dir is None:
        held = lock_new_dir(Path(cfg.run_dir) if cfg.run_dir else default_run_dir(cfg), is_writer)
    else:
        checkpoint = resume_point(resume_dir, cfg)
        finished = is_complete(resume_dir, checkpoint, cfg, RUN_SUMMARY)
        if checkpoint is not None:
            rundir.check_metrics([resume_dir / METRICS], checkpoint.iteration, finished)
        if finished:
            return report_complete(resume_dir, checkpoint)
        held = lock_resumed_dir(resume_dir, checkpoint, is_writer)
    warn(cfg)  # every input accepted: what runs, but probably not as meant
    with locked(held):
        restart_if_no_checkpoint(held, [held.run_dir / METRICS, held.run_dir / "tb"] if held.run_dir else [])
        if held.run_dir:
            write_run_config(held.run_dir, cfg, held.resumed)
        if not record_start(held, f"run dir {held.run_dir}", stop):
            return Launched(exit_status(None, stop), held.run_dir, None)
        summary = train(cfg, held.run_dir, resume=held.checkpoint, stop=stop, callbacks=callbacks)
    return Launched(exit_status(summary, stop), held.run_dir, summary)


def read_train_config(argv: Sequence[str]) -> tuple[Config, Path | None]:
    """The config of `argv` and, for ``resume=DIR``, the run directory (its stored config with
    the other items as overrides); raises `ConfigError` naming the bad item."""
    resume_dir, rest = split_resume(list(argv))
    cli.check_unique(list(argv))
    if resume_dir is None:
        return parse_overrides(list(argv)), None
    rundir.refuse_sweep_for_train(Path(resume_dir))
    return resume_config(resume_dir, rest)


def describe_train(argv: Sequence[str]) -> str:
    """What a dry run prints: the resolved config as ``config.yaml`` would hold it, and where the
    run would write. Parsed and checked as a run's input is; nothing is created or written, and
    the devices, the memory and the run directory are not checked."""
    cfg, run_dir = read_train_config(argv)
    warn(cfg)
    return (
        config_text(cfg).rstrip()
        + "\n"
        + dry_run_line(cfg, run_dir, default_run_dir(cfg), run_dir is not None)
    )


def default_run_dir(cfg: Config) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{task_label(cfg.env)}-{cfg.algo}-{cfg.explore}-s{cfg.seed}-{stamp}"


def write_run_config(run_dir: Path, cfg: Config, resumed: bool) -> None:
    """``config.yaml``: a new run's, or a resumed one's when its budget or W&B changed."""
    if not resumed:
        write_config(run_dir, cfg)
        return
    stored = load_config(run_dir)
    if (cfg.total_steps, cfg.wandb) != (stored.total_steps, stored.wandb):
        write_config(run_dir, cfg)  # an extended budget, or W&B turned on or off: the run's own now


def launch_sweep(argv: Sequence[str], stop: StopRequest) -> Launched:
    """Runs the command line `argv` of ``python -m coherent_jax.sweep``: parse, check, prepare
    the sweep's directory, run the grid, exit status. Raises one of `BAD_INPUT`."""
    plan, resume_dir = read_sweep(argv)
    cfg = plan.base
    supervised = preflight(cfg, SWEEP_MODULE, argv)
    if supervised is not None:
        return Launched(supervised, None, None)
    from coherent_jax.run.training import check_sweep, run_sweep  # lazy: JAX; bad input goes without

    is_writer = check_sweep(plan)
    if resume_dir is None:
        held = lock_new_dir(Path(cfg.run_dir) if cfg.run_dir else default_sweep_dir(cfg), is_writer)
    else:
        checkpoint = resume_point(resume_dir, cfg, resume_dir / plan.points[0].name / METRICS)
        finished = is_complete(resume_dir, checkpoint, cfg, SWEEP_SUMMARY)
        if checkpoint is not None:
            sweep.check_rows(resume_dir, [p.name for p in plan.points], checkpoint, finished)
        if finished:
            return report_complete(resume_dir, checkpoint)
        held = lock_resumed_dir(resume_dir, checkpoint, is_writer)
    warn(cfg)
    with locked(held):
        if held.run_dir:
            restart_if_no_checkpoint(
                held, [held.run_dir / p.name / f for p in plan.points for f in (METRICS, "tb")]
            )
            write_grid(held.run_dir, plan, held.resumed)
        if not record_start(held, f"sweep dir {held.run_dir}: {len(plan.points)} points", stop):
            return Launched(exit_status(None, stop), held.run_dir, None)
        summary = run_sweep(plan, held.run_dir, resume=held.checkpoint, stop=stop)
    return Launched(exit_status(summary, stop), held.run_dir, summary)


def describe_sweep(argv: Sequence[str]) -> str:
    """What a dry run prints: the resolved config and the grid as YAML, and where the sweep would
    write; nothing is created or written, the devices and the memory are not checked."""
    plan, run_dir = read_sweep(argv)
    warn(plan.base)
    grid = {"grid": {"axes": plan.axes, "seeds": plan.seeds, "points": len(plan.points)}}
    text = config_text(plan.base) + yaml.safe_dump(grid, sort_keys=False, default_flow_style=None)
    return (
        text.rstrip()
        + "\n"
        + dry_run_line(plan.base, run_dir, default_sweep_dir(plan.base), run_dir is not None)
    )


def default_sweep_dir(cfg: Config) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"sweep-{task_label(cfg.env)}-{cfg.algo}-{cfg.explore}-{stamp}"


def write_grid(run_dir: Path, plan: SweepPlan, resumed: bool) -> None:
    """The shared ``config.yaml`` and, for a new sweep, ``grid.json``."""
    write_config(run_dir, dataclasses.replace(plan.base, run_dir=str(run_dir)))
    if not resumed:
        grid = {"axes": plan.axes, "seeds": plan.seeds}
        atomic_write(run_dir / rundir.GRID, json.dumps(grid, indent=2).encode())


def preflight(cfg: Config, module: str, argv: Sequence[str]) -> int | None:
    """Checks before the devices: W&B importable with ``wandb=true``. With ``distributed=true``
    on the first process, runs the supervisor of ``python -m module argv`` and returns its exit
    status; None: this process runs the command itself."""
    if cfg.wandb:
        wandb_preflight()
    if multihost.needs_supervisor(cfg.distributed):
        return multihost.supervise(module, list(argv))
    return None


def lock_new_dir(path: Path, is_writer: bool) -> HeldDir:
    """A new run's directory `path` made and locked (refused while another process holds it);
    nothing for a process that does not write."""
    if not is_writer:
        return HeldDir(None, resumed=False)
    rundir.refuse_if_held(path, "run_dir")
    created = rundir.first_missing(path)
    run_dir = prepare_output_dir(path)
    return HeldDir(run_dir, False, None, rundir.acquire(run_dir, "run_dir"), created)


def is_complete(run_dir: Path, checkpoint: Checkpoint | None, cfg: Config, summary_file: str) -> bool:
    """Whether a resumed run is done: its checkpoint at the budget and its summary written."""
    return (
        checkpoint is not None
        and checkpoint.iteration >= cfg.num_iterations
        and (run_dir / summary_file).exists()
    )


def report_complete(run_dir: Path, checkpoint: Checkpoint) -> Launched:
    """A resume of a complete run: says so; nothing runs, exit status 0."""
    print(f"{PREFIX} {run_dir} is already complete ({checkpoint.iteration} iterations)")
    return Launched(EXIT_OK, run_dir, None)


def lock_resumed_dir(run_dir: Path, checkpoint: Checkpoint | None, is_writer: bool) -> HeldDir:
    """A resumed run's directory locked (refused while another process holds it)."""
    if not is_writer:
        return HeldDir(None, True, checkpoint)
    return HeldDir(run_dir, True, checkpoint, rundir.acquire(run_dir, "resume"))


def warn(cfg: Config) -> None:
    """The warnings of a config that runs but probably not as meant, one line each on stderr."""
    warning = warmup_warning(cfg)
    if warning is not None:
        print(warning, file=sys.stderr, flush=True)


@contextlib.contextmanager
def locked(held: HeldDir) -> Iterator[HeldDir]:
    """`held`'s lock for the run's length; a W&B run that does not start (`TrackingError`)
    leaves nothing behind a new run (its directory removed again), a resumed one its rows."""
    with held.lock or contextlib.nullcontext():
        try:
            yield held
        except TrackingError:
            if held.run_dir is not None and not held.resumed:
                rundir.discard_new_dir(held.run_dir, held.created)
            raise


def restart_if_no_checkpoint(held: HeldDir, outputs: list[Path]) -> None:
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


def record_start(held: HeldDir, line: str, stop: StopRequest) -> bool:
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


def dry_run_line(cfg: Config, run_dir: Path | None, default: Path, resumed: bool) -> str:
    """A dry run's last line: nothing written, and where the run would write."""
    verb = "continue in" if resumed else "write to"
    return f"# dry run: nothing written; the run would {verb} {run_dir or Path(cfg.run_dir or default)}"
