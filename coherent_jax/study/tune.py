"""A study's ``tune:`` block: each strategy tuned with the same budget before it is evaluated.

A comparison of exploration strategies is fair only when each is tuned with the same
budget. The block gives each strategy (by its label) a search space over its own
settings, and one budget for all::

    tune:
      method: grid          # grid (the default): one vmapped sweep per strategy; or optuna
      budget: 4             # candidates per strategy: at most this many grid points, or trials
      seeds: 2              # tuning seeds per candidate: seed, seed+1, ... (default 2)
      seed: 1000            # the first tuning seed (default 1000), disjoint from the evaluation's
      metric: auc           # auc (the default) or final: what picks the winner
      per_task: false       # true: a choice per task; false: one across the tasks
      total_steps: 100000   # env steps per tuning seed (default: the study's), or one per algo
      space:
        coherent: {coherent.beta: [0.0, 0.01, 0.1, 1.0]}
        pink: {pink.exponent: [0.5, 1.0, 1.5]}                   # optuna only: not sweepable
        action: {lr: {low: 0.0001, high: 0.01, log: true}}      # optuna only: a range

A strategy's *unit* is one of its evaluation cells (``TASK/ALGO/LABEL``) before tuning; its
tuning runs in ``TASK/ALGO/LABEL@tune``. With ``grid`` that is one cell whose sweep vmaps
the space's grid x the tuning seeds (one compiled program); with ``optuna`` one cell per
trial (``TASK/ALGO/LABEL@tune/tNNN``), `coherent_jax.study.optuna_search`. The evaluation
cells then run at each strategy's chosen values (`with_items`); the stage itself is
`coherent_jax.study.tune_run`.

`check` refuses, in one line before anything runs: an unknown label or key, a grid larger
than the budget, a key method grid cannot vary in one program (naming it, and optuna), a
range with grid, method optuna without its optional dependency, several tasks with one
Optuna choice across them, and tuning seeds that overlap any cell's evaluation seeds.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import itertools
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from coherent_jax.config import FIELDS, SWEEPABLE, Config, ConfigError, sweepable
from coherent_jax.config.parse import modern_items, modern_key
from coherent_jax.run.rundir import read_metrics
from coherent_jax.run.sweep import parse_sweep
from coherent_jax.study import curves
from coherent_jax.study.cell import Cell, StudyError, progress

TUNE_KEYS = ("method", "budget", "seeds", "seed", "metric", "per_task", "total_steps", "space")
METHODS = ("grid", "optuna")
TUNE_METRICS = ("auc", "final")
FIRST_SEED = 1000
DEFAULT_SEEDS = 2
RANGE_KEYS = ("low", "high", "log")
# What a strategy's search space may not vary: what its cells are (task, algorithm,
# strategy), the budget, the seeds, and where and how a run writes.
NOT_TUNABLE = (
    "env", "algo", "explore", "preset", "seed", "total_steps", "eval_every", "eval_episodes", "run_dir",
    "progress", "checkpoint_every", "resume", "tensorboard", "wandb", "wandb_init_timeout", "num_devices",
    "distributed", "physics_threads",
)  # fmt: skip
OPTUNA_EXTRA = 'pip install -e ".[optuna]"'
SUFFIX = "@tune"


@dataclasses.dataclass(frozen=True)
class Range:
    """Optuna's range of one key: ``low`` to ``high``, on a log scale or not; integers when
    both ends are."""

    low: float
    high: float
    log: bool = False

    @property
    def integer(self) -> bool:
        """Whether Optuna draws integers (both ends are)."""
        return isinstance(self.low, int) and isinstance(self.high, int)


Dimension = tuple[Any, ...] | Range  # a grid's (or a categorical) values, or a range


@dataclasses.dataclass(frozen=True)
class Tune:
    """The ``tune:`` block: method, budget, tuning seeds, metric, and each label's space."""

    method: str
    budget: int
    seeds: tuple[int, ...]
    metric: str
    per_task: bool
    total_steps: dict[str, int] | None
    space: dict[str, dict[str, Dimension]]

    def spec(self) -> dict[str, Any]:
        """What the block says, as JSON (``tune.json`` and the fingerprint hold it)."""
        space = {
            label: {k: dataclasses.asdict(d) if isinstance(d, Range) else list(d) for k, d in dims.items()}
            for label, dims in self.space.items()
        }
        return {
            "method": self.method, "budget": self.budget, "seeds": list(self.seeds), "metric": self.metric,
            "per_task": self.per_task, "total_steps": self.total_steps, "space": space,
        }  # fmt: skip


# ------------------------------------------------------------------ reading the block
def text(value: Any) -> str:
    """A value as the command line writes it: ``true``, ``0.001``, ``[16,16]``."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, list | tuple):
        return "[" + ",".join(text(v) for v in value) + "]"
    return str(value)


def _whole(value: Any, what: str, least: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise StudyError(f"invalid value for {what!r}: {value!r} (allowed: an integer >= {least})")
    return value


def _number(value: Any) -> Any:
    """YAML reads ``1e-4`` (no dot) as text: a number's text as its number, else as it is."""
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def _dimension(label: str, key: str, value: Any) -> Dimension:
    what = f"tune.space.{label}.{key}"
    if isinstance(value, list) and value and len(value) == len({text(v) for v in value}):
        return tuple(value)
    if isinstance(value, Mapping) and {"low", "high"} <= set(value) and set(value) <= set(RANGE_KEYS):
        low, high, log = _number(value["low"]), _number(value["high"]), value.get("log", False)
        numbers = all(isinstance(x, int | float) and not isinstance(x, bool) for x in (low, high))
        if numbers and low < high and isinstance(log, bool) and (not log or low > 0):
            return Range(low, high, log)
    raise StudyError(
        f"invalid value for {what!r}: {value!r} (allowed: a non-empty list of distinct values, or for "
        "method optuna a range {low: A, high: B, log: true|false} with A < B, and A > 0 on a log scale)"
    )


def _space(value: Any) -> dict[str, dict[str, Dimension]]:
    if not isinstance(value, Mapping) or not value:
        raise StudyError(
            f"invalid value for 'tune.space': {value!r} (allowed: a mapping label -> {{key: values}})"
        )
    space = {}
    for label, dims in value.items():
        if not isinstance(dims, Mapping) or not dims:
            raise StudyError(
                f"invalid value for 'tune.space.{label}': {dims!r} (allowed: a mapping key -> values)"
            )
        space[str(label)] = {str(k): _dimension(str(label), str(k), v) for k, v in dims.items()}
    return space


def make_tune(value: Any, steps_table) -> Tune:
    """The block's `Tune` (`steps_table`: the study's reading of ``total_steps``); `StudyError`
    for a bad key or value."""
    if not isinstance(value, Mapping):
        raise StudyError(
            f"invalid value for 'tune': {value!r} (allowed: a mapping of {', '.join(TUNE_KEYS)})"
        )
    unknown = sorted(set(value) - set(TUNE_KEYS))
    if unknown:
        raise StudyError(f"unknown key {unknown[0]!r} in 'tune' (allowed: {', '.join(TUNE_KEYS)})")
    method = value.get("method", "grid")
    if method not in METHODS:
        raise StudyError(f"invalid value for 'tune.method': {method!r} (allowed: {', '.join(METHODS)})")
    metric = value.get("metric", "auc")
    if metric not in TUNE_METRICS:
        raise StudyError(f"invalid value for 'tune.metric': {metric!r} (allowed: {', '.join(TUNE_METRICS)})")
    per_task = value.get("per_task", False)
    if not isinstance(per_task, bool):
        raise StudyError(f"invalid value for 'tune.per_task': {per_task!r} (allowed: true or false)")
    space = _space(value.get("space"))
    if "budget" in value or method == "optuna":
        budget = _whole(value.get("budget"), "tune.budget", 1)
    else:  # a grid's budget: its largest space
        budget = max(grid_size(dims) for dims in space.values())
    count = _whole(value.get("seeds", DEFAULT_SEEDS), "tune.seeds", 1)
    first = _whole(value.get("seed", FIRST_SEED), "tune.seed", 0)
    steps = None if value.get("total_steps") is None else steps_table(value["total_steps"])
    if (
        steps is not None
        and isinstance(value["total_steps"], Mapping)
        and "default" not in value["total_steps"]
    ):
        del steps["default"]  # an algorithm it does not name tunes at its cells' own budget
    seeds = tuple(range(first, first + count))
    return Tune(method, budget, seeds, metric, per_task, steps, space)


def grid_size(dims: Mapping[str, Dimension]) -> int:
    """Points of a space's grid (a range counts as one: grid refuses ranges)."""
    return math.prod(len(d) if isinstance(d, tuple) else 1 for d in dims.values())


def candidates(dims: Mapping[str, Dimension]) -> list[dict[str, Any]]:
    """The grid's points in the order a sweep runs them (the first key outermost)."""
    return [dict(zip(dims, combo, strict=True)) for combo in itertools.product(*dims.values())]


# ------------------------------------------------------------------ the cells of the tuning
def pair(cell: Cell) -> tuple[str, str]:
    """The cell's (algo, explore): which keys it reads, and what an old key is now."""
    return cell.setting("algo", "ppo") or "ppo", cell.setting("explore", "action") or "action"


def with_items(cell: Cell, items: Sequence[str], name: str | None = None, seeds: int | None = None) -> Cell:
    """`cell` with `items` replacing its overrides of the same keys (a sweep takes each key once),
    under `name` and with `seeds` if given."""
    keys = {modern_key(i.split("=", 1)[0], note=False, pair=pair(cell)) for i in items}
    kept = [
        o for o in cell.overrides if modern_key(o.split("=", 1)[0], note=False, pair=pair(cell)) not in keys
    ]
    return Cell(cell.suite, name or cell.name, (*kept, *items), cell.seeds if seeds is None else seeds)


def keys_of(tune: Tune, label: str, cell: Cell) -> dict[str, Dimension]:
    """The label's space with its keys as they are now (``beta`` -> ``coherent.beta``)."""
    return {modern_key(k, note=False, pair=pair(cell)): d for k, d in tune.space[label].items()}


def steps(tune: Tune, cell: Cell) -> int:
    """Env steps per tuning seed: the block's for the cell's algorithm, else the cell's own."""
    table = tune.total_steps or {}
    own = table.get(pair(cell)[0], table.get("default"))
    return int(own if own is not None else cell.setting("total_steps") or Config().total_steps)


def units(tune: Tune, cells: Sequence[Cell]) -> list[Cell]:
    """The evaluation cells (before tuning) whose strategy the block tunes."""
    return [c for c in cells if c.label in tune.space]


def base_items(tune: Tune, unit: Cell) -> list[str]:
    """What every tuning cell of the unit sets: the tuning's budget and its first seed."""
    return [f"total_steps={steps(tune, unit)}", f"seed={tune.seeds[0]}"]


def grid_cell(tune: Tune, unit: Cell) -> Cell:
    """The unit's tuning cell for method grid: its space's grid x the tuning seeds, one sweep."""
    dims = keys_of(tune, unit.label, unit)
    axes = [f"{k}={text(list(v))}" for k, v in dims.items()]
    return with_items(unit, [*base_items(tune, unit), *axes], unit.name + SUFFIX, len(tune.seeds))


def trial_cell(tune: Tune, unit: Cell, number: int, values: Mapping[str, Any]) -> Cell:
    """Trial `number` of the unit's Optuna search: the tuning seeds at `values`, one sweep."""
    items = [*base_items(tune, unit), *(f"{k}={text(v)}" for k, v in values.items())]
    return with_items(unit, items, f"{unit.name}{SUFFIX}/t{number:03d}", len(tune.seeds))


def tuning_cells(tune: Tune, cells: Sequence[Cell]) -> list[Cell]:
    """Method grid's tuning cells (none for optuna: its trials are made as it runs)."""
    return [grid_cell(tune, u) for u in units(tune, cells)] if tune.method == "grid" else []


def fingerprint(tune: Tune, cells: Sequence[Cell]) -> str:
    """The block and its units' specifications: a ``tune.json`` of another is not this study's."""
    spec = {"tune": tune.spec(), "units": [u.spec() for u in units(tune, cells)]}
    return hashlib.sha256(json.dumps(spec, sort_keys=True, default=str).encode()).hexdigest()[:16]


# ------------------------------------------------------------------ scores
def seed_curves(study_dir: Path, cell: Cell) -> list[list[tuple[int, float]]]:
    """Each point's evaluation curve (env steps, return), points in order: from its
    ``metrics.jsonl``, else from the study's curves table."""
    table = curves.table_runs(curves.table_path(study_dir))
    found = []
    for point in curves.point_dirs(Path(study_dir) / cell.name / "sweep"):
        log = point / curves.LOG
        rows = read_metrics(log) if log.is_file() else table.get((cell.name, point.name), [])
        found.append(
            [(int(r["env_steps"]), float(r[curves.EVAL])) for r in rows if r.get(curves.EVAL) is not None]
        )
    return found


def seed_score(curve: Sequence[tuple[int, float]], metric: str) -> float:
    """One seed's score: its last evaluation return (``final``) or the mean over training
    (``auc``: trapezoid over env steps, as the report's); -inf without a finite evaluation."""
    if not curve or not all(math.isfinite(v) for _, v in curve):
        return -math.inf
    if metric == "final" or len(curve) < 2:
        return curve[-1][1]
    area = sum((s1 - s0) * (v0 + v1) / 2 for (s0, v0), (s1, v1) in itertools.pairwise(curve))
    return area / (curve[-1][0] - curve[0][0])


def spent_steps(cell: Cell, study_dir: Path) -> int:
    """The env steps a tuning cell ran, over all its points (a pruned trial's, to where it stopped)."""
    return int(round(progress(cell, study_dir)[0] * cell.env_steps))


def mean_score(curves_: Sequence[Sequence[tuple[int, float]]], metric: str) -> float:
    """A candidate's score: the mean of its seeds' (-inf if any seed has none)."""
    scores = [seed_score(c, metric) for c in curves_]
    return -math.inf if not scores or -math.inf in scores else sum(scores) / len(scores)


# ------------------------------------------------------------------ checks
def optuna_installed() -> bool:
    """Whether Optuna can be imported (the optional extra ``optuna``)."""
    try:
        return importlib.util.find_spec("optuna") is not None
    except ValueError:  # sys.modules["optuna"] is None: its import is blocked
        return False


def evaluation_seeds(cell: Cell) -> range:
    """The seeds a cell's sweep runs: its ``seed`` (default 0) and the ``seeds - 1`` after it."""
    first = int(cell.setting("seed") or Config().seed)
    return range(first, first + cell.seeds)


def _check_seeds(tune: Tune, cells: Sequence[Cell]) -> None:
    for c in cells:
        shared = sorted(set(tune.seeds) & set(evaluation_seeds(c)))
        if shared:
            ev = evaluation_seeds(c)
            raise StudyError(
                f"invalid value for 'tune.seeds': tuning seeds {tune.seeds[0]}..{tune.seeds[-1]} overlap the "
                f"evaluation seeds {ev[0]}..{ev[-1]} of cell {c.name!r} at seed {shared[0]} (allowed: seeds "
                f"disjoint from the evaluation's; tune.seed: K starts the tuning seeds at K)"
            )


def _check_key(tune: Tune, label: str, key: str, cell: Cell) -> None:
    where = f"tune.space.{label}"
    if key not in FIELDS or key in NOT_TUNABLE:
        raise StudyError(
            f"unknown key {key!r} in {where} (allowed: a training key of the strategy's, not "
            f"{', '.join(NOT_TUNABLE[:6])}, ...; python -m coherent_jax.train --help lists them)"
        )
    if tune.method != "grid":
        return
    algo, explore = pair(cell)
    own = [k for k in SWEEPABLE if sweepable(k).read_by(algo, explore)]
    if key not in own:
        raise StudyError(
            f"invalid key {key!r} in {where} with method grid: algo={algo} explore={explore} cannot vary it "
            f"within one vmapped program (allowed with grid: {', '.join(own)}; method: optuna tunes any key)"
        )
    if any(isinstance(d, Range) for d in tune.space[label].values()):
        raise StudyError(
            f"invalid value for {where!r}: a range with method grid (allowed: lists of values; "
            "ranges with method: optuna)"
        )


def _parse(cell: Cell, label: str) -> None:
    """Parses a tuning cell as its sweep will (a value out of range is refused)."""
    try:
        parse_sweep([*modern_items(cell.overrides, note=False), f"seeds={cell.seeds}"])
    except ConfigError as exc:
        raise StudyError(f"tune.space.{label}: {exc}") from None


def _corners(dims: Mapping[str, Dimension]) -> list[dict[str, Any]]:
    """Each value of each key (a range's ends), the others at their first: what `check` parses."""
    first = {k: d[0] if isinstance(d, tuple) else d.low for k, d in dims.items()}
    ends = {k: d if isinstance(d, tuple) else (d.low, d.high) for k, d in dims.items()}
    return [{**first, k: v} for k, vs in ends.items() for v in vs]


def check(tune: Tune, cells: Sequence[Cell], labels: Sequence[str]) -> None:
    """Refuses a bad block before anything runs (`cells`: the study's, before tuning)."""
    unknown = sorted(set(tune.space) - set(labels))
    if unknown:
        raise StudyError(f"unknown strategy {unknown[0]!r} in tune.space (allowed: {', '.join(labels)})")
    if tune.method == "optuna" and not optuna_installed():
        raise StudyError(
            f"invalid value for 'tune.method': optuna is not installed (allowed: {OPTUNA_EXTRA}, "
            "the optional extra optuna; or method: grid)"
        )
    tasks = sorted({c.name.split("/", 1)[0] for c in units(tune, cells)})
    if tune.method == "optuna" and not tune.per_task and len(tasks) > 1:
        raise StudyError(
            f"invalid value for 'tune.per_task': false with method optuna and {len(tasks)} tasks "
            "(allowed: per_task: true, a choice per task; or method: grid, whose choice spans the tasks)"
        )
    _check_seeds(tune, cells)
    for label, dims in tune.space.items():
        if tune.method == "grid" and grid_size(dims) > tune.budget:
            raise StudyError(
                f"invalid value for 'tune.space.{label}': a grid of {grid_size(dims)} candidates exceeds "
                f"tune.budget {tune.budget} (allowed: at most {tune.budget} candidates per strategy)"
            )
        for unit in [u for u in units(tune, cells) if u.label == label]:
            for key in keys_of(tune, label, unit):
                _check_key(tune, label, key, unit)
            if tune.method == "grid":
                _parse(grid_cell(tune, unit), label)
            else:
                for values in _corners(keys_of(tune, label, unit)):
                    _parse(trial_cell(tune, unit, 0, values), label)
