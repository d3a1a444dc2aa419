"""What a cell still costs: its compute estimated from its own logs, from finished cells of
the same kind beside it, from a probe of its program (`coherent_jax.study.plan`) or from
rough defaults; and ``--status``, each cell's state with the compute it still needs."""

from __future__ import annotations

import json
import statistics
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import NamedTuple

from coherent_jax.run.rundir import cpu_info
from coherent_jax.study.cell import Cell, cell_dir, cell_state, measured_rate, progress

# Rough env steps/s of one point, used when no cell of the same task and algorithm has
# finished yet and no probe measured it
# (docs/benchmarks.md: PPO 64 envs on native physics; coherent about 0.3-0.5x of it).
# SAC's figure is at UTD 1 and scales with 1 / utd_ratio (measured: the thesis suite's SAC budget).
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
# What a cell costs besides its env steps, before it has run: the sweep's start, compile and
# evaluations (``wall_s - train_s`` of its ``sweep.json``). Used when no finished cell of the
# same kind says: the medians of the committed cells (experiments/results/, 2026-12:
# PPO 99.5 s over 85 cells, A2C 99.8 s over 47, SAC 407.6 s over 27, whose evaluations
# run 1,000-step episodes).
DEFAULT_START_S = {"ppo": 100.0, "a2c": 100.0, "sac": 400.0}


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
    """A finished cell, its measured env steps/s, the CPU model it ran on (None if unknown)
    and its seconds besides training (start, compile, evaluations; None if not recorded)."""

    cell: Cell
    rate: float
    cpu_model: str | None
    fixed_s: float | None = None


def _fixed_seconds(sweep: Path) -> float | None:
    """``wall_s - train_s`` of a finished sweep: its seconds besides training, or None."""
    try:
        summary = json.loads((sweep / "sweep.json").read_text())
        return max(0.0, float(summary["wall_s"]) - float(summary["train_s"]))
    except (OSError, KeyError, TypeError, ValueError):
        return None


def _cpu_model(sweep: Path) -> str | None:
    """The CPU model a sweep recorded in its ``versions.json``, or None."""
    try:
        model = json.loads((sweep / "versions.json").read_text()).get("cpu_model")
    except (OSError, ValueError, AttributeError):
        return None
    return model if isinstance(model, str) else None


def finished_cells(root: Path) -> list[Finished]:
    """Every finished cell of every study under ``root`` (a folder of studies: the study's
    own and those beside it) with its measured rate and CPU."""
    found = []
    for spec_file in sorted(Path(root).glob("*/**/cell.json")):
        sweep = spec_file.parent / "sweep"
        rate = measured_rate(sweep)
        if rate is None:
            continue
        try:
            spec = json.loads(spec_file.read_text())["spec"]
            cell = Cell(spec["suite"], spec["name"], tuple(spec["overrides"]), int(spec["seeds"]))
        except (OSError, KeyError, TypeError, ValueError):
            continue
        found.append(Finished(cell, rate, _cpu_model(sweep), _fixed_seconds(sweep)))
    return found


def _this_cpu_first(found: list[Finished]) -> list[Finished]:
    """Those of `found` that ran on this machine's CPU model if there are any, else all of
    them (rates differed about twofold between the CPUs the suites ran on)."""
    here = cpu_info()["cpu_model"]
    return [f for f in found if here is not None and f.cpu_model == here] or found


def default_rate(cell: Cell) -> float:
    """`DEFAULT_RATE` or `TASK_RATE` over the cell's `_cost`."""
    algo = cell.setting("algo", "ppo")
    base = TASK_RATE.get(cell.setting("env", ""), DEFAULT_RATE.get(algo, 5000.0))
    if algo == "sac":
        base /= float(cell.setting("utd_ratio", "1.0"))
    return base / _cost(cell)


def estimated_seconds(
    cell: Cell, study_dir: Path, probed: Mapping[str, float] | None = None, kin: list[Finished] | None = None
) -> float:
    """Compute the cell still needs.

    From its own measured rate once it has one (a finished cell's ``sweep.json``, a
    stopped, carried or running cell's logged iterations: a coherent episode cell's cost
    follows its episodes' lengths, which no other cell's rate shows); else from a probe of
    its program (``probed``: cell name -> env steps/s, `coherent_jax.study.plan`); else from
    the finished cells of the same task, algorithm, minibatches and preset (any study beside
    this one), those that ran on this machine's CPU model if there are any (rates differed
    about twofold between the CPUs the suites ran on): those of the same strategy (and
    coherent gradient, integration and layers) as they ran, or if there are none, every one
    rescaled by `_cost` to this cell's strategy (median over them); else from the defaults
    above. Vmapped points share the cores, so a cell's total rate is about one point's,
    whatever its points. ``kin``: the finished cells, if already read.
    """
    fraction, rate = progress(cell, study_dir)
    if rate is None and probed and cell.name in probed:
        rate = probed[cell.name]
    if rate is None:
        every = finished_cells(Path(study_dir).parent) if kin is None else kin
        kin = _this_cpu_first([f for f in every if _kind(f.cell) == _kind(cell)])
        same = [f.rate for f in kin if _strategy(f.cell) == _strategy(cell)]
        if same:
            rate = statistics.median(same)
        elif kin:
            rate = statistics.median([f.rate * _cost(f.cell) / _cost(cell) for f in kin])
        else:
            rate = default_rate(cell)
    return (1.0 - fraction) * cell.env_steps / rate


def start_seconds(cell: Cell, study_dir: Path, kin: list[Finished] | None = None) -> float:
    """What a cell that has not started costs besides its env steps (0 once it has): the
    median ``wall_s - train_s`` of the finished cells of its kind (`_kind`), those of this
    CPU model if any; else of the finished cells of its own study (same machine, same
    evaluation settings: a closer guess than other studies' cells of other kinds); else
    `DEFAULT_START_S`. A study of small cells is mostly this."""
    if (cell_dir(cell, study_dir) / "sweep").exists() or progress(cell, study_dir)[0] > 0:
        return 0.0
    every = [
        f for f in (finished_cells(Path(study_dir).parent) if kin is None else kin) if f.fixed_s is not None
    ]
    same = _this_cpu_first([f for f in every if _kind(f.cell) == _kind(cell)])
    same = same or [f for f in every if f.cell.suite == cell.suite]
    if same:
        return statistics.median(f.fixed_s for f in same)
    return DEFAULT_START_S.get(cell.setting("algo", "ppo"), 100.0)


def status(cells: Iterable[Cell], study_dir: Path) -> str:
    """``--status``: per cell its state, progress and compute still needed; then the total."""
    lines, left = [], 0.0
    kin = finished_cells(Path(study_dir).parent)
    for cell in cells:
        state = cell_state(cell, study_dir)
        fraction, _ = progress(cell, study_dir)
        need = (
            0.0
            if state == "done"
            else estimated_seconds(cell, study_dir, kin=kin) + start_seconds(cell, study_dir, kin)
        )
        left += need
        lines.append(
            f"{cell.name:44s} {state:8s} {100 * fraction:5.1f}%  "
            f"{cell.env_steps / 1e6:6.2f}M env steps  needs ~{need / 3600:6.2f} h"
        )
    lines.append(
        f"total still needed: ~{left / 3600:.1f} h on this machine (estimates until a cell finishes)"
    )
    return "\n".join(lines)
