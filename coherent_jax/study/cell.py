"""A cell of a study: one (task, algorithm, strategy, settings) run for N seeds as one vmapped
sweep (``python -m coherent_jax.sweep ... seeds=N``); its specification, where its results
live, its state (done, running, stopped, carried or missing) and the sweep that runs it.

A cell's directory is ``STUDY_DIR/CELL/`` (``CELL`` is ``TASK/ALGO/LABEL``):

* ``cell.json``: its specification and fingerprint (the first 16 hex digits of the SHA-256
  of the specification); a directory written for another specification is refused;
* ``sweep/``: the sweep's directory (``sweep.json`` once finished, one run directory per
  point with ``config.yaml``, ``metrics.jsonl``, ``summary.json``; ``versions.json``);
* ``run.log``: the sweep's output; ``running.pid``: the sweep's process while it runs (and
  the machine it runs on, for a cluster's).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import socket
import sys
from pathlib import Path
from typing import Any

from coherent_jax.config.parse import modern_items
from coherent_jax.run.rundir import holder
from coherent_jax.study import carry
from coherent_jax.study.curves import point_dirs

SPEC_VERSION = 1  # bump when the meaning of a cell's overrides changes
# The folder that holds the package: the sweeps a study starts read this package, whatever
# else is installed (a checkout's results are made by its own code).
PACKAGE_ROOT = Path(__file__).resolve().parents[2]
CELL_RECORD = "cell.json"
PID_FILE = "running.pid"
LOG = "run.log"


@dataclasses.dataclass(frozen=True)
class Cell:
    """One (task, algorithm, strategy, settings) run for ``seeds`` seeds as one sweep.

    ``suite`` is the name of the study the cell belongs to (a suite of experiments/studies/
    is one); ``name`` is ``TASK/ALGO/LABEL``, its directory in the study's."""

    suite: str
    name: str
    overrides: tuple[str, ...]
    seeds: int

    def spec(self) -> dict[str, Any]:
        """What the fingerprint covers (``cell.json`` stores it)."""
        return {
            "version": SPEC_VERSION,
            "suite": self.suite,
            "name": self.name,
            "overrides": list(self.overrides),
            "seeds": self.seeds,
        }

    @property
    def fingerprint(self) -> str:
        """The first 16 hex digits of the SHA-256 of `spec` (``cell.json`` stores it)."""
        return hashlib.sha256(json.dumps(self.spec(), sort_keys=True).encode()).hexdigest()[:16]

    def setting(self, key: str, default: str | None = None) -> str | None:
        """The value of override ``key`` (the last one wins), or ``default``."""
        for item in reversed(self.overrides):
            k, _, v = item.partition("=")
            if k == key:
                return v
        return default

    @property
    def label(self) -> str:
        """The strategy's label in the study (the name's last part: ``coherent-beta0``)."""
        return self.name.split("/", 2)[-1]

    @property
    def env_steps(self) -> int:
        """Env steps of the whole cell (every seed and every grid point)."""
        points = self.seeds
        for item in self.overrides:
            _, _, v = item.partition("=")
            if v.startswith("[") and not v.startswith("[["):
                if item.split("=", 1)[0] not in ("policy_hidden", "value_hidden"):
                    points *= len(v.strip("[]").split(","))
        return int(self.setting("total_steps", "0")) * points


class StudyError(ValueError):
    """Bad input: one line, exit status 2."""


def cell_dir(cell: Cell, study_dir: Path) -> Path:
    """``STUDY_DIR/TASK/ALGO/LABEL``."""
    return Path(study_dir) / cell.name


def read_record(path: Path) -> dict[str, Any]:
    """A ``cell.json``'s content; `StudyError` if it cannot be read."""
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise StudyError(f"unreadable cell record {str(path)!r}: {exc}") from None


def check_cell_dir(cell: Cell, study_dir: Path) -> None:
    """Refuses a results directory written for another specification of the cell."""
    path = cell_dir(cell, study_dir) / CELL_RECORD
    if not path.exists():
        return
    stored = read_record(path)
    if stored.get("fingerprint") != cell.fingerprint:
        raise StudyError(
            f"results directory {str(path.parent)!r} holds cell {cell.name!r} of another specification "
            f"(stored {stored.get('spec')}, now {cell.spec()}); move it away to recompute the cell"
        )


# ------------------------------------------------------------------ state of a cell
def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists (one of another user counts; a zombie, ended but not yet
    reaped by its new parent, does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def running_pid(cell: Cell, study_dir: Path) -> int | None:
    """The live process ``running.pid`` names (the cell's sweep), or None.

    The file holds the pid and, when a cluster's node wrote it (``executor=ray``), that
    machine's name: a sweep on another machine counts as running while it holds its folder's
    lock (`coherent_jax.run.rundir.holder`, a lock on the shared filesystem)."""
    lock = cell_dir(cell, study_dir) / PID_FILE
    try:
        fields = lock.read_text().split()
        pid = int(fields[0])
    except (ValueError, IndexError, OSError):
        return None
    if len(fields) > 1 and fields[1] != socket.gethostname():
        return pid if holder(cell_dir(cell, study_dir) / "sweep") is not None else None
    return pid if _pid_alive(pid) else None


def cell_state(cell: Cell, study_dir: Path) -> str:
    """done | running | stopped | carried | missing (carried: stopped elsewhere, its state in
    the cell's carry file, `carry`)."""
    d = cell_dir(cell, study_dir)
    if (d / "sweep" / "sweep.json").exists():
        return "done"
    if running_pid(cell, study_dir) is not None:
        return "running"
    if (d / "sweep").exists():
        return "stopped"
    return "carried" if carry.carry_path(d).is_file() else "missing"


def progress(cell: Cell, study_dir: Path) -> tuple[float, float | None]:
    """(fraction of env steps done, measured env steps/s of the whole cell or None)."""
    sweep = cell_dir(cell, study_dir) / "sweep"
    if (sweep / "sweep.json").exists():
        return 1.0, measured_rate(sweep)
    if sweep.exists():
        logs = (p / "metrics.jsonl" for p in point_dirs(sweep))
        texts = [f.read_text() for f in logs if f.exists()]
    else:  # a carried cell's logs are in its carry file
        texts = [b.decode() for b in carry.carried_metrics(sweep.parent).values()]
    done, rates = 0, []
    for text in texts:
        lines = [json.loads(x) for x in text.splitlines() if x.strip().endswith("}")]
        done += max((r.get("env_steps", 0) for r in lines), default=0)
        rates.append(_logged_rate(lines))
    rate = sum(rates) if rates and None not in rates else None
    return (done / cell.env_steps if cell.env_steps else 0.0), rate


def _logged_rate(rows: list[dict]) -> float | None:
    """One point's env steps/s between its first and last logged iteration, or None.

    ``time_s`` runs on across resumes, so the span covers every stretch the point ran,
    less the first iteration's compilation; the points of a vmapped cell run together,
    so their rates add up to the cell's."""
    timed = [(r["env_steps"], r["time_s"]) for r in rows if "env_steps" in r and "time_s" in r]
    if len(timed) < 2 or timed[-1][1] <= timed[0][1]:
        return None
    return (timed[-1][0] - timed[0][0]) / (timed[-1][1] - timed[0][1])


def measured_rate(sweep: Path) -> float | None:
    """Env steps/s of the whole cell (all points together), as its sweep recorded it."""
    try:
        return float(json.loads((sweep / "sweep.json").read_text())["sweep_env_steps_per_s"])
    except (OSError, KeyError, TypeError, ValueError):
        return None


# ------------------------------------------------------------------ running a cell
def sweep_command(cell: Cell, study_dir: Path) -> list[str]:
    """The sweep that runs (or, if its directory exists, continues) the cell."""
    sweep = (cell_dir(cell, study_dir) / "sweep").absolute()
    if sweep.exists():
        return [sys.executable, "-m", "coherent_jax.sweep", f"resume={sweep}"]
    # A cell's specification keeps the flat keys it was defined with (its fingerprint, and so
    # its results, stay valid); the sweep is given their grouped names, with no note.
    return [
        sys.executable,
        "-m",
        "coherent_jax.sweep",
        *modern_items(cell.overrides, note=False),
        f"seeds={cell.seeds}",
        f"run_dir={sweep}",
    ]


def sweep_env() -> dict[str, str]:
    """The environment of a cell's sweep: this package first on the path."""
    return dict(os.environ, PYTHONPATH=str(PACKAGE_ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def prepare(cell: Cell, study_dir: Path) -> list[str]:
    """Makes the cell's directory ready to run (its ``cell.json``, a carried state unpacked)
    and returns the sweep's command."""
    d = cell_dir(cell, study_dir)
    check_cell_dir(cell, study_dir)
    d.mkdir(parents=True, exist_ok=True)
    carry.unpack(d)  # a cell carried from elsewhere continues from its checkpoint
    cmd = sweep_command(cell, study_dir)
    if not (d / CELL_RECORD).exists():
        record = {"spec": cell.spec(), "fingerprint": cell.fingerprint, "command": " ".join(cmd)}
        tmp = d / (CELL_RECORD + ".tmp")
        tmp.write_text(json.dumps(record, indent=2) + "\n")
        os.replace(tmp, d / CELL_RECORD)
    return cmd
