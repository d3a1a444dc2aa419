"""The host loop's records and what ends it early.

What the loop runs (`Job`), a run in progress (`Session`, its compiled `Programs`), how it
ended (`Outcome`); a request to stop after the current iteration, from SIGINT/SIGTERM or a
callback (`StopRequest`), and a divergence (`DivergenceError`, raised by the loop's guard,
`coherent_jax.run.loop.check_finite`). No JAX: the commands install the stop request before
anything slow.
"""

from __future__ import annotations

import dataclasses
import math
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from coherent_jax.agents.trainer import Trainer
from coherent_jax.config import Config
from coherent_jax.run.checkpoint import LoopState
from coherent_jax.run.rundir import PREFIX


@dataclasses.dataclass(frozen=True)
class Job:
    """What the loop runs.

    Attributes:
      cfg: the settings every point shares (shapes, schedule, outputs).
      trainer: `coherent_jax.agents.make_trainer`'s object for `cfg`.
      seeds: one seed per point (a single run: one).
      names: one name per point, for messages.
      run_dir: where the checkpoint lives (None: nothing is written).
      point_dirs: per point, where its metrics, TensorBoard files, parameters and
        summary go (a single run: ``[run_dir]``).
      hparams: a sweep's stacked hyperparameters (leading axis: points); None for a
        single run, whose state is not vmapped.
      label: how the start-up line names the job.
      trackers: per point, a W&B run receiving each of its rows (`coherent_jax.run.outputs.WandbRun`,
        ``wandb=true``); empty: none.
      callbacks: a single run's `coherent_jax.run.outputs.Callback`s, called with each row.
    """

    cfg: Config
    trainer: Trainer
    seeds: list[int]
    names: list[str]
    run_dir: Path | None
    point_dirs: list[Path] | None
    hparams: Any = None
    label: str = ""
    trackers: Sequence[Any] = ()
    callbacks: Sequence[Any] = ()

    @property
    def points(self) -> bool:
        return self.hparams is not None

    @property
    def num_points(self) -> int:
        return len(self.seeds)


@dataclasses.dataclass
class Outcome:
    """How the loop ended.

    Attributes:
      state: the final train state (stacked for a sweep).
      loop: the loop's state (timers; per-point last returns and evaluations).
      start, done: the iteration it started after and the last one done.
      compile_s: seconds of compilation in this process.
      num_devices: devices the work was spread over.
      physics: the physics engine the trainer's env resolved to.
      stopped_by: the signal's name when SIGINT/SIGTERM ended it early, ``"callback"`` when
        a callback did (``stop_reason`` says why), else None.
      last_return, last_eval: per point (lists of length num_points).
      diverged: per diverged point (index), the reason.
      wall_s: seconds since the run began, over all its sessions.
    """

    state: Any
    loop: LoopState
    start: int
    done: int
    compile_s: float
    num_devices: int
    physics: str
    stopped_by: str | None
    last_return: list[float]
    last_eval: dict[str, list[float]]
    diverged: dict[int, str]
    wall_s: float
    stop_reason: str | None = None


class Programs(NamedTuple):
    """The compiled programs of a run (vmapped over the points for a sweep)."""

    iteration: Callable  # state -> (state, metrics)
    evaluate: Callable  # (state, key) -> evaluation metrics
    check_params: Callable  # state -> whether every parameter is finite
    split: Callable  # key -> two keys (the next evaluation key and this evaluation's)


@dataclasses.dataclass
class Session:
    """A run in progress: what the loop's steps read and update.

    Attributes:
      job: what runs.
      num_devices, physics: the devices it is spread over; the engine of its env.
      state, shardings: the train state (stacked for a sweep) and its placement.
      key: the evaluation key (one per point for a sweep).
      loop: the loop's state as a checkpoint stores it.
      start: the iteration the session started after (0, or the checkpoint's).
      resumed: whether it continues from a checkpoint.
      t_start, t_compile: when the session began; when its compile (init included) began.
      elapsed_before: seconds of the run's earlier sessions.
      programs, compile_s: the compiled programs and the seconds they took.
      last_return, last_eval, diverged: per point, the latest episode return (float64
        [n]), the latest evaluation's metrics, the reasons of the diverged points.
      files, writers, bar, checkpoints: the metrics files, TensorBoard writers, progress
        bar, and whether this process takes part in writing checkpoints.
      done, saved, stopping: the last iteration done, the last one checkpointed (-1:
        none), the signal number all processes agreed to stop on (0: none).
    """

    job: Job
    num_devices: int
    physics: str
    state: Any
    shardings: Any
    key: Any
    loop: LoopState
    start: int
    resumed: bool
    t_start: float
    t_compile: float
    elapsed_before: float = 0.0
    programs: Programs | None = None
    compile_s: float = 0.0
    last_return: Any = None
    last_eval: dict[str, Any] = dataclasses.field(default_factory=dict)
    diverged: dict[int, str] = dataclasses.field(default_factory=dict)
    files: list[Any] = dataclasses.field(default_factory=list)
    writers: list[Any] = dataclasses.field(default_factory=list)
    bar: Any = None
    checkpoints: bool = False
    done: int = 0
    saved: int = -1
    stopping: int = 0


def to_float(x: Any) -> float | None:
    """A metric as JSON has it: a float, or None when not finite."""
    value = float(x)
    return value if math.isfinite(value) else None


class DivergenceError(RuntimeError):
    """A loss or a parameter became non-finite; the message names the iteration and the quantity."""


class EnvError(RuntimeError):
    """A task's own env raised mid-run (a Gymnasium env on the host); the message names the env,
    the iteration and the env's error, and the checkpoint a resume starts from."""


def env_error(run: Session, it: int) -> EnvError | None:
    """`EnvError` in one line if a Gymnasium env of the run (training's or evaluation's host
    pool) raised during iteration `it`, naming the env, the iteration, its error and the
    checkpoint a resume starts from; None if the failure was not an env's."""
    from coherent_jax.envs.host_gym import host_pool  # lazy: this module loads without JAX (launch)

    trainer = run.job.trainer
    pools = (host_pool(getattr(trainer, "env", None)), host_pool(getattr(trainer, "eval_env", None)))
    failure = next((p.failure for p in pools if p is not None and p.failure), None)
    if failure is None:
        return None
    where = run.job.run_dir
    if where is None:
        kept = ""
    elif run.saved > 0:
        kept = f"; the checkpoint of iteration {run.saved} is kept: fix the env, then resume={where}"
    else:
        kept = f"; no checkpoint yet: fix the env, then resume={where} starts it over"
    return EnvError(f"at iteration {it}, {failure}{kept}")


CALLBACK = "callback"  # a summary's ``stopped_by`` when a callback stopped the run


class StopRequest:
    """Turns SIGINT/SIGTERM, or a callback's `request`, into a request to stop after the
    current iteration.

    Installed before anything slow (imports, compiles), so a Ctrl-C at any moment
    ends the program cleanly instead of with a traceback. A second signal ends the
    process at once, by the signal's default action. ``signum`` is the signal's number;
    ``reason`` what a callback said (`coherent_jax.run.outputs`).
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self.reason: str | None = None
        self._previous: dict[int, Any] = {}

    def request(self, reason: str) -> None:
        """A callback's request to stop after the current iteration (the first reason is kept)."""
        if self.reason is None:
            self.reason = reason

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is not None:
            signal.signal(signum, signal.SIG_DFL)
            signal.raise_signal(signum)
            return
        self.signum = signum
        print(
            f"\n{PREFIX} {signal.Signals(signum).name}: stopping after the current step",
            file=sys.stderr,
            flush=True,
        )

    @property
    def name(self) -> str | None:
        return signal.Signals(self.signum).name if self.signum is not None else None

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
