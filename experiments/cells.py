"""A cell of the reproduction (`reproduce.py`): its specification, where its results
live, their state (done, running, stopped, carried or missing) with the compute still
needed, and the sweep that runs it.

A cell's directory is ``RESULTS/SUITE/CELL/``: ``cell.json`` (its specification and
fingerprint), ``sweep/`` (the sweep's directory: ``sweep.json`` once finished, one run
directory per point) and ``run.log`` (the sweep's output).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any, NamedTuple

import carry  # beside this file (reproduce.py puts it on sys.path)
from curves import point_dirs as _point_dirs

from coherent_jax.config.parse import modern_items
from coherent_jax.run.rundir import cpu_info

SPEC_VERSION = 1  # bump when the meaning of a cell's overrides changes

# Rough env steps/s of one point, used by --status when no cell of the same task and
# algorithm has finished yet
# (docs/benchmarks.md: PPO 64 envs on native physics; coherent about 0.3-0.5x of it).
# SAC's figure is at UTD 1 and scales with 1 / utd_ratio (measured: reproduce.SAC_STEPS).
DEFAULT_RATE = {"ppo": 6000.0, "a2c": 8000.0, "sac": 150.0}
# Tasks whose own rate differs from the locomotion tasks' (PPO, action noise, measured).
TASK_RATE = {
    "dmc-cartpole_swingup_sparse": 22000.0,
    "dmc-acrobot_swingup_sparse": 20000.0,
    "dmc-ball_in_cup": 19000.0,  # native MuJoCo (physics=auto on a CPU); 11.9k on MJX
    "dmc-finger_turn_hard": 25000.0,  # native; 17.3k on MJX
    "mountain_car_continuous": 24900.0,  # pure JAX, at the classic suite's 16 envs
}
# A2C/PPO iteration time relative to action noise. SAC's strategies cost about the same
# as its action noise (HalfCheetah, one seed: coherent 0.93x, psne 1.05x): its updates
# dominate, and they do not depend on the strategy.
# Lattice: `python -m benchmarks strategies env=halfcheetah` (2026-12-04, idle
# machine) measured 2.02x, beside gSDE's 1.28x (docs/benchmarks.md).
STRATEGY_COST = {"coherent": 2.5, "noisynet": 1.5, "psne": 2.2, "gsde": 1.3, "pink": 1.1, "lattice": 2.0}
# coherent.gradient=episode re-infers each segment's episode prefix in the loss: 22x the
# exact mode's iteration at the defaults before the blocks ahead of the minibatch's
# earliest episode start were skipped, 1.64x less since (HalfCheetah, over one episode
# cycle, interleaved in one process; docs/benchmarks.md, "Long chains").
EPISODE_GRADIENT_COST = 13.5


@dataclasses.dataclass(frozen=True)
class Cell:
    """One (task, algorithm, strategy, settings) run for ``seeds`` seeds as one sweep."""

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
    def env_steps(self) -> int:
        """Env steps of the whole cell (every seed and every grid point)."""
        points = self.seeds
        for item in self.overrides:
            _, _, v = item.partition("=")
            if v.startswith("[") and not v.startswith("[["):
                if item.split("=", 1)[0] not in ("policy_hidden", "value_hidden"):
                    points *= len(v.strip("[]").split(","))
        return int(self.setting("total_steps", "0")) * points


class ReproduceError(ValueError):
    """Bad input: one line, exit status 2."""


def cell_dir(cell: Cell, results: Path) -> Path:
    """``results/SUITE/CELL``."""
    return results / cell.suite / cell.name


def check_cell_dir(cell: Cell, results: Path) -> None:
    """Refuses a results directory written for another specification of the cell."""
    path = cell_dir(cell, results) / "cell.json"
    if not path.exists():
        return
    try:
        stored = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ReproduceError(f"unreadable cell record {str(path)!r}: {exc}") from None
    if stored.get("fingerprint") != cell.fingerprint:
        raise ReproduceError(
            f"results directory {str(path.parent)!r} holds cell {cell.name!r} of another specification "
            f"(stored {stored.get('spec')}, now {cell.spec()}); move it away to recompute the cell"
        )


# ------------------------------------------------------------------ state of a cell
def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists (one of another user counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def cell_state(cell: Cell, results: Path) -> str:
    """done | running | stopped | carried | missing (carried: stopped elsewhere, its state in
    the cell's carry file, `carry`)."""
    d = cell_dir(cell, results)
    if (d / "sweep" / "sweep.json").exists():
        return "done"
    lock = d / "running.pid"
    if lock.exists():
        try:
            if _pid_alive(int(lock.read_text().split()[0])):
                return "running"
        except (ValueError, IndexError, OSError):
            pass
    if (d / "sweep").exists():
        return "stopped"
    return "carried" if carry.carry_path(d).is_file() else "missing"


def progress(cell: Cell, results: Path) -> tuple[float, float | None]:
    """(fraction of env steps done, measured env steps/s of the whole cell or None)."""
    sweep = cell_dir(cell, results) / "sweep"
    if (sweep / "sweep.json").exists():
        return 1.0, _measured_rate(sweep)
    if sweep.exists():
        logs = (p / "metrics.jsonl" for p in _point_dirs(sweep))
        texts = [f.read_text() for f in logs if f.exists()]
    else:  # a carried cell's logs are in its carry file
        texts = [b.decode() for b in carry.carried_metrics(sweep.parent).values()]
    done, rates = 0, []
    for text in texts:
        lines = [json.loads(x) for x in text.splitlines() if x.strip()]
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


def _measured_rate(sweep: Path) -> float | None:
    """Env steps/s of the whole cell (all points together), as its sweep recorded it."""
    try:
        return float(json.loads((sweep / "sweep.json").read_text())["sweep_env_steps_per_s"])
    except (OSError, KeyError, TypeError, ValueError):
        return None


def _cost(cell: Cell) -> float:
    """Iteration time relative to action noise (1 for SAC, whose updates dominate)."""
    if cell.setting("algo", "ppo") == "sac":
        return 1.0
    cost = STRATEGY_COST.get(cell.setting("explore", "action") or "action", 1.0)
    return cost * (EPISODE_GRADIENT_COST if cell.setting("coherent.gradient") == "episode" else 1.0)


def _kind(cell: Cell) -> tuple[str | None, ...]:
    """What sets a cell's rate apart from its strategy: task, algorithm, SAC's UTD, the
    minibatches, and the preset (``preset=thesis`` runs 4 envs x 1,000 steps with up to 80
    full-batch steps)."""
    keys = ("env", "algo", "utd_ratio", "num_minibatches", "preset")
    return tuple(cell.setting(k, "ppo" if k == "algo" else None) for k in keys)


def _strategy(cell: Cell) -> tuple[str | None, ...]:
    """The settings of a cell's strategy that change its cost (beta and the like do not)."""
    keys = ("coherent.gradient", "coherent.integration", "coherent.layers")
    return (cell.setting("explore", "action"), *(cell.setting(k) for k in keys))


class Finished(NamedTuple):
    """A finished cell, its measured env steps/s and the CPU model it ran on (None if unknown)."""

    cell: Cell
    rate: float
    cpu_model: str | None


def _cpu_model(sweep: Path) -> str | None:
    """The CPU model a sweep recorded in its ``versions.json``, or None."""
    try:
        model = json.loads((sweep / "versions.json").read_text()).get("cpu_model")
    except (OSError, ValueError, AttributeError):
        return None
    return model if isinstance(model, str) else None


def _finished_cells(results: Path) -> list[Finished]:
    """Every finished cell under ``results`` (any suite) with its measured rate and CPU."""
    found = []
    for spec_file in sorted(results.glob("*/**/cell.json")):
        sweep = spec_file.parent / "sweep"
        rate = _measured_rate(sweep)
        if rate is None:
            continue
        try:
            spec = json.loads(spec_file.read_text())["spec"]
            cell = Cell(spec["suite"], spec["name"], tuple(spec["overrides"]), int(spec["seeds"]))
        except (OSError, KeyError, TypeError, ValueError):
            continue
        found.append(Finished(cell, rate, _cpu_model(sweep)))
    return found


def estimated_seconds(cell: Cell, results: Path) -> float:
    """Compute the cell still needs.

    From its own measured rate once it has one (a finished cell's ``sweep.json``, a
    stopped, carried or running cell's logged iterations: a coherent episode cell's cost
    follows its episodes' lengths, which no other cell's rate shows); else from the
    finished cells of the same task, algorithm, minibatches and preset (any suite), those
    that ran on this machine's CPU model if there are any (rates differed about twofold
    between the CPUs the suites ran on): those of the same strategy (and coherent
    gradient, integration and layers) as they ran, or if there are none, every one
    rescaled by `_cost` to this cell's strategy (median over them); else from the
    defaults above. Vmapped points share the cores, so a cell's total rate is about one
    point's, whatever its points.
    """
    fraction, rate = progress(cell, results)
    if rate is None:
        kin = [f for f in _finished_cells(results) if _kind(f.cell) == _kind(cell)]
        here = cpu_info()["cpu_model"]
        kin = [f for f in kin if here is not None and f.cpu_model == here] or kin
        same = [f.rate for f in kin if _strategy(f.cell) == _strategy(cell)]
        if same:
            rate = statistics.median(same)
        elif kin:
            rate = statistics.median([f.rate * _cost(f.cell) / _cost(cell) for f in kin])
        else:
            algo = cell.setting("algo", "ppo")
            base = TASK_RATE.get(cell.setting("env", ""), DEFAULT_RATE.get(algo, 5000.0))
            if algo == "sac":
                base /= float(cell.setting("utd_ratio", "1.0"))
            rate = base / _cost(cell)
    return (1.0 - fraction) * cell.env_steps / rate


def status(cells: Iterable[Cell], results: Path) -> str:
    """``--status``: per cell its state, progress and compute still needed; then the total."""
    lines, left = [], 0.0
    for cell in cells:
        state = cell_state(cell, results)
        fraction, _ = progress(cell, results)
        need = 0.0 if state == "done" else estimated_seconds(cell, results)
        left += need
        lines.append(
            f"{cell.name:44s} {state:8s} {100 * fraction:5.1f}%  "
            f"{cell.env_steps / 1e6:6.2f}M env steps  needs ~{need / 3600:6.2f} h"
        )
    lines.append(
        f"total still needed: ~{left / 3600:.1f} h on this machine (estimates until a cell finishes)"
    )
    return "\n".join(lines)


# ------------------------------------------------------------------ running a cell
ROOT = Path(__file__).resolve().parents[1]


def sweep_command(cell: Cell, results: Path) -> list[str]:
    sweep = cell_dir(cell, results) / "sweep"
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


def run_cell(cell: Cell, results: Path, log=print) -> int:
    d = cell_dir(cell, results)
    check_cell_dir(cell, results)
    d.mkdir(parents=True, exist_ok=True)
    carry.unpack(d)  # a cell carried from elsewhere continues from its checkpoint
    record = {
        "spec": cell.spec(),
        "fingerprint": cell.fingerprint,
        "command": " ".join(sweep_command(cell, results)),
    }
    if not (d / "cell.json").exists():
        (d / "cell.json").write_text(json.dumps(record, indent=2) + "\n")
    (d / "running.pid").write_text(f"{os.getpid()}\n")
    cmd = sweep_command(cell, results)
    log(f"[reproduce] {cell.suite} {cell.name}: {' '.join(cmd[1:])}")
    t0 = time.time()
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    try:
        with open(d / "run.log", "a") as out:
            code = subprocess.call(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
    finally:
        (d / "running.pid").unlink(missing_ok=True)
    log(f"[reproduce] {cell.name}: exit {code} after {time.time() - t0:.0f} s")
    return code
