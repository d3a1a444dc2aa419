"""Weights & Biases mirror of a run: ``wandb=true`` (the optional extra ``pip install -e ".[wandb]"``).

A run with ``wandb=true`` logs to one W&B run per training run (per grid point in a
sweep, grouped by the sweep's directory name):

* the resolved config (`config.to_dict`, exactly what ``config.yaml`` records), once;
* every metrics row the run writes to ``metrics.jsonl``, at ``step`` = the iteration;
* evaluation videos (``python -m coherent_jax.evaluate RUN_DIR video=true`` on such a
  run attaches its video to the same W&B run);
* the final summary (``summary.json``) as the W&B run's summary.

It never needs the network: unless ``WANDB_MODE`` is set in the environment, the mode
is ``offline`` and everything stays in ``RUN_DIR/wandb/`` (``wandb sync RUN_DIR/wandb/offline-run-*``
uploads it later). ``WANDB_MODE=online`` (after ``wandb login``) logs live.

The W&B run id is drawn once and kept in ``RUN_DIR/wandb-run.json``; ``resume=RUN_DIR``
and ``evaluate`` reopen the same id with ``resume="allow"``, so a resumed run continues
the same W&B run. A resumed run recomputes the iterations after its checkpoint
bit-identically, so rows logged again for those steps carry the values already logged.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

PROJECT = "coherent_jax"
RUN_FILE = "wandb-run.json"
INSTALL_HINT = 'wandb=true needs Weights & Biases: pip install -e ".[wandb]"'


class TrackingError(RuntimeError):
    """W&B was asked for and cannot be used (one line: what and how to fix it)."""


def available() -> bool:
    """Whether the optional ``wandb`` package is importable."""
    try:
        import wandb  # noqa: F401
    except ImportError:
        return False
    return True


def require() -> None:
    """Raises `TrackingError` with the install command when ``wandb`` is missing."""
    if not available():
        raise TrackingError(INSTALL_HINT)


def mode() -> str:
    """``WANDB_MODE`` when the user set it, else ``offline``: a run never needs the network."""
    return os.environ.get("WANDB_MODE") or "offline"


def _identity(run_dir: Path, name: str, group: str | None) -> dict[str, Any]:
    """The W&B run's id, name and group, drawn once and then read from ``RUN_FILE``."""
    path = run_dir / RUN_FILE
    if path.exists():
        return json.loads(path.read_text())
    identity = {"id": secrets.token_hex(4), "project": PROJECT, "name": name, "group": group}
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(identity, indent=1) + "\n")
    tmp.replace(path)
    return identity


class WandbRun:
    """One W&B run mirroring one training run (or one grid point of a sweep)."""

    def __init__(self, run: Any) -> None:
        self._run = run

    @classmethod
    def open(
        cls,
        run_dir: Path,
        config: Mapping[str, Any] | None,
        name: str,
        group: str | None = None,
    ) -> WandbRun:
        """Starts (or, with an id in ``run_dir/RUN_FILE``, resumes) the W&B run of ``run_dir``.

        ``config`` is logged as the run's config (None: leave it as logged before,
        for a process such as `evaluate` that only adds media).
        """
        require()
        import wandb

        identity = _identity(run_dir, name, group)
        settings = wandb.Settings(silent=True, console="off", x_disable_stats=True)
        run = wandb.init(
            project=identity["project"],
            id=identity["id"],
            name=identity["name"],
            group=identity["group"],
            dir=str(run_dir),
            mode=mode(),
            resume="allow",
            config=dict(config) if config is not None else None,
            settings=settings,
            reinit="create_new",
        )
        return cls(run)

    def log(self, row: Mapping[str, float | None], step: int) -> None:
        """One metrics row at ``step`` (the iteration); None values (no evaluation) are left out."""
        self._run.log({k: v for k, v in row.items() if v is not None}, step=int(step))

    def video(self, path: Path, step: int | None, key: str = "eval/video") -> None:
        """An evaluation video (MP4 or GIF) at ``step`` (None: W&B's next step, after every row
        already logged, which a resumed W&B run requires of a late addition)."""
        import wandb

        fmt = "gif" if Path(path).suffix == ".gif" else "mp4"
        self._run.log({key: wandb.Video(str(path), format=fmt)}, step=None if step is None else int(step))

    def finish(self, summary: Mapping[str, Any] | None = None) -> None:
        """Writes ``summary`` (the run's ``summary.json``) as the W&B summary and closes the run."""
        if summary:
            for key, value in summary.items():
                self._run.summary[key] = value
        self._run.finish()


class Mirrors:
    """The W&B runs of a run's points (empty without ``wandb=true``) and their final summaries.

    ``runs[j]`` mirrors point j (a single run: one); the loop logs each point's rows to it
    (`coherent_jax.loop.sink_metrics`). The caller sets ``summaries`` once it has written
    them; `mirrored` then finishes each run with its own.
    """

    def __init__(self, runs: list[WandbRun]) -> None:
        self.runs = runs
        self.summaries: Sequence[Mapping[str, Any]] | None = None


@contextlib.contextmanager
def mirrored(
    points: Sequence[tuple[Path, Mapping[str, Any], str]], group: str | None = None
) -> Iterator[Mirrors]:
    """Opens one `WandbRun` per (directory, config, name) of `points`, and finishes them all on exit.

    Finished with their summaries when the caller set them (the run completed), else
    without (stopped, diverged: a resume continues the same W&B runs). Nothing is opened
    for no points, so a run without ``wandb=true`` never imports ``wandb``.
    """
    mirrors = Mirrors([WandbRun.open(d, config, name, group) for d, config, name in points])
    try:
        yield mirrors
    finally:
        for j, run in enumerate(mirrors.runs):
            run.finish(mirrors.summaries[j] if mirrors.summaries else None)
