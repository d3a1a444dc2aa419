"""The host loop's records: what it runs (`Job`), a run in progress (`Session`), how it ended (`Outcome`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from coherent_jax.agents.trainer import Trainer
from coherent_jax.config import Config
from coherent_jax.run.runs import LoopState


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
      trackers: per point, a W&B run receiving each of its rows (`coherent_jax.run.tracking.WandbRun`,
        ``wandb=true``); empty: none.
      callbacks: a single run's `coherent_jax.run.callbacks.Callback`s, called with each row.
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
