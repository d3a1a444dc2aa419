"""A study, from its file or its command line, to its cells.

A study file (YAML) declares what to compare and how; the command line takes the same
keys (``env=[gym:Pusher-v5,hopper] explore=[action,coherent,pink] seeds=10``), and with a
file its items override the file's::

    name: pusher                 # the study's name (default: the file's stem)
    out: studies/pusher          # its folder (default: studies/NAME), relative to the file
    seeds: 10                    # seeds per cell, vmapped in one sweep
    total_steps: 500000          # per seed; or by algorithm: {ppo: 1000000, sac: 200000}
    tasks: [gym:Pusher-v5, hopper, envs.py:TargetLine]   # or {label: env}, or
                                 # {label: {env: E, settings: {ppo: [...]}}}
    algos: [ppo]                 # (the default) or {a2c: [lr=0.003]}: each algorithm's own settings
    strategies:                  # names, or label -> explore, its settings, the algorithms it runs with
      action: {}
      coherent: {}
      pink-0.5: {explore: pink, settings: [pink.exponent=0.5]}
    settings: [num_envs=16]      # every cell's (training keys, as on the command line)
    evaluation: {episodes: 10, every: 5}   # eval_episodes, eval_every
    metrics: [final, auc, reach] # reach: the seeds that ever reached a sparse reward or goal, and when
    compare: [coherent > pink, coherent > action]   # the claims the report judges
    grids: [...]                 # optional: several blocks of tasks x algos x strategies, each
                                 # with its own tasks, algos, strategies, settings, total_steps
    tune: {...}                  # optional: each strategy tuned with one budget first
                                 # (`coherent_jax.study.tune`)

A cell is one (task, algorithm, strategy) of a block: ``TASK/ALGO/LABEL``, run for
``seeds`` seeds as one sweep. Its overrides are, in this order: ``env``, ``algo``,
``explore``, ``total_steps``, the block's settings, the evaluation's, the task's for the
algorithm, the algorithm's, the strategy's. Paths (``out``, a user's env file) are
relative to the study file's folder, where the sweeps run; on the command line, to the
current folder. `check` refuses bad input in one line before anything is written
(`coherent_jax.study.cell.StudyError`), parsing each cell as its sweep will.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from coherent_jax import strategies
from coherent_jax.config import Config, ConfigError
from coherent_jax.config.parse import modern_items
from coherent_jax.run.sweep import parse_sweep
from coherent_jax.study import tune as tune_spec
from coherent_jax.study.cell import Cell, StudyError

METRICS = ("final", "auc", "reach")
FILE_KEYS = (
    "name", "out", "seeds", "total_steps", "tasks", "algos", "strategies", "settings",
    "evaluation", "metrics", "compare", "grids", "tune",
)  # fmt: skip
GRID_KEYS = ("tasks", "algos", "strategies", "settings", "total_steps", "evaluation")
EVALUATION = {"episodes": "eval_episodes", "every": "eval_every"}


@dataclasses.dataclass(frozen=True)
class Strategy:
    """A strategy under its label: its ``explore=`` value, its settings, the algorithms it runs
    with in its block (None: all of the block's)."""

    label: str
    explore: str
    settings: tuple[str, ...] = ()
    algos: tuple[str, ...] | None = None


@dataclasses.dataclass(frozen=True)
class Grid:
    """One block: tasks (label -> env, with per-algorithm settings) x algorithms x strategies."""

    tasks: dict[str, str]
    task_settings: dict[str, dict[str, tuple[str, ...]]]
    algos: dict[str, tuple[str, ...]]
    strategies: tuple[Strategy, ...]
    settings: tuple[str, ...]
    total_steps: dict[str, int]  # algorithm (or "default") -> env steps per seed


@dataclasses.dataclass(frozen=True)
class Comparison:
    """``better > than``: the claim that strategy ``better`` improves on ``than``."""

    better: str
    than: str

    def __str__(self) -> str:
        return f"{self.better} > {self.than}"


@dataclasses.dataclass(frozen=True)
class Study:
    """A study: its name, folder, the folder its sweeps run in, its blocks and seeds, what its
    report measures and judges; its ``tune:`` block and, once the tuning is done, the values
    it chose (cell name -> ``key=value`` items its evaluation cell takes)."""

    name: str
    out: Path
    base: Path
    seeds: int
    grids: tuple[Grid, ...]
    metrics: tuple[str, ...]
    comparisons: tuple[Comparison, ...]
    tune: tune_spec.Tune | None = None
    chosen: Mapping[str, tuple[str, ...]] | None = None

    def cells(self, tuned: bool = True) -> list[Cell]:
        """The evaluation cells: at the values the tuning chose (`tuned`, once it is done), or
        at their own settings."""
        cells = [c for g in self.grids for c in grid_cells(self, g)]
        if not tuned or not self.chosen:
            return cells
        return [tune_spec.with_items(c, self.chosen.get(c.name, ())) for c in cells]

    def labels(self) -> list[str]:
        """Every strategy label, in the order first declared."""
        return list(dict.fromkeys(s.label for g in self.grids for s in g.strategies))


def grid_cells(study: Study, grid: Grid) -> list[Cell]:
    """The block's cells: tasks, then algorithms, then strategies (those that run with it)."""
    cells = []
    for task, env in grid.tasks.items():
        for algo, algo_settings in grid.algos.items():
            steps = grid.total_steps.get(algo, grid.total_steps["default"])
            for s in grid.strategies:
                if s.algos is not None and algo not in s.algos:
                    continue
                overrides = (
                    f"env={env}",
                    f"algo={algo}",
                    f"explore={s.explore}",
                    f"total_steps={steps}",
                    *grid.settings,
                    *grid.task_settings.get(task, {}).get(algo, ()),
                    *algo_settings,
                    *s.settings,
                )
                cells.append(Cell(study.name, f"{task}/{algo}/{s.label}", overrides, study.seeds))
    return cells


# ------------------------------------------------------------------ reading the declarations
def task_label(env: str) -> str:
    """A task's label in cell names: a registry name as it is, ``gym:Pusher-v5`` -> ``Pusher-v5``,
    ``envs.py:TargetLine`` -> ``TargetLine``."""
    name = env.rsplit(":", 1)[-1]
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", name).strip("-.") or "task"


def _text(value: Any) -> str:
    """A YAML value as the command line writes it: ``true``, ``0.5``, ``[16,16]``."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, list):
        return "[" + ",".join(_text(v) for v in value) + "]"
    return str(value)


def _items(value: Any, what: str) -> tuple[str, ...]:
    """Settings: a list of ``key=value`` strings, or a mapping key -> value."""
    if value is None:
        return ()
    if isinstance(value, Mapping):
        return tuple(f"{k}={_text(v)}" for k, v in value.items())
    if isinstance(value, list) and all(isinstance(v, str) and "=" in v for v in value):
        return tuple(value)
    raise StudyError(
        f"invalid value for {what!r}: {value!r} (allowed: a list of key=value items, or a mapping key: value)"
    )


def _names(value: Any, what: str) -> list[str]:
    """A name or a list of names (``[a,b]`` on the command line)."""
    if isinstance(value, str):
        value = [v.strip() for v in value.strip("[]").split(",")] if value.startswith("[") else [value]
    if not isinstance(value, list) or not value or not all(isinstance(v, str) and v for v in value):
        raise StudyError(
            f"invalid value for {what!r}: {value!r} (allowed: a name or a non-empty list of names)"
        )
    return value


def _tasks(value: Any) -> tuple[dict[str, str], dict[str, dict[str, tuple[str, ...]]]]:
    """label -> env, and label -> algorithm -> settings."""
    if not isinstance(value, Mapping):
        envs = _names(value, "tasks")
        labels = [task_label(e) for e in envs]
        twice = sorted({x for x in labels if labels.count(x) > 1})
        if twice:
            raise StudyError(
                f"invalid value for 'tasks': two tasks are named {twice[0]!r} "
                "(allowed: distinct names; give each a label: tasks: {label: env})"
            )
        return dict(zip(labels, envs, strict=True)), {}
    envs, settings = {}, {}
    for label, entry in value.items():
        if isinstance(entry, str) or entry is None:
            envs[str(label)] = entry or str(label)
            continue
        if not isinstance(entry, Mapping) or set(entry) - {"env", "settings"}:
            raise StudyError(
                f"invalid value for task {label!r}: {entry!r} "
                "(allowed: an env, or env: and settings: by algorithm)"
            )
        envs[str(label)] = str(entry.get("env", label))
        by_algo = entry.get("settings") or {}
        settings[str(label)] = {a: _items(s, f"tasks.{label}.settings.{a}") for a, s in by_algo.items()}
    return envs, settings


def _algos(value: Any) -> dict[str, tuple[str, ...]]:
    if isinstance(value, Mapping):
        algos = {str(a): _items(s, f"algos.{a}") for a, s in value.items()}
    else:
        algos = {a: () for a in _names(value, "algos")}
    for a in algos:
        if a not in strategies.ALGOS:
            raise StudyError(f"invalid value for 'algos': {a!r} (allowed: {', '.join(strategies.ALGOS)})")
    return algos


def _strategy(label: str, entry: Any) -> Strategy:
    """One strategy: a registry name or variant (``coherent-mc``), or label -> its declaration."""
    if entry is None or entry == {}:
        try:
            explore, *variant = strategies.overrides(label)
        except ValueError:
            raise StudyError(
                f"unknown strategy {label!r} (allowed: {', '.join(strategies.EXPLORES)}, "
                "or label: {explore: NAME, settings: [...]})"
            ) from None
        return Strategy(label, explore.split("=", 1)[1], tuple(variant))
    if not isinstance(entry, Mapping) or set(entry) - {"explore", "settings", "algos"}:
        raise StudyError(
            f"invalid value for strategy {label!r}: {entry!r} (allowed: explore:, settings:, algos:)"
        )
    explore = str(entry.get("explore", label))
    if explore not in strategies.EXPLORES:
        raise StudyError(f"unknown strategy {explore!r} (allowed: {', '.join(strategies.EXPLORES)})")
    algos = entry.get("algos")
    return Strategy(
        label, explore, _items(entry.get("settings"), f"strategies.{label}.settings"),
        None if algos is None else tuple(_names(algos, f"strategies.{label}.algos")),
    )  # fmt: skip


def _strategies(value: Any) -> tuple[Strategy, ...]:
    if isinstance(value, Mapping):
        return tuple(_strategy(str(k), v) for k, v in value.items())
    return tuple(_strategy(n, None) for n in _names(value, "strategies"))


def _steps(value: Any) -> dict[str, int]:
    table = dict(value) if isinstance(value, Mapping) else {} if value is None else {"default": value}
    table.setdefault("default", Config().total_steps)
    for v in table.values():
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise StudyError(
                f"invalid value for 'total_steps': {v!r} (allowed: an integer >= 1, or one per algo)"
            )
    return {str(k): int(v) for k, v in table.items()}


def _evaluation(value: Any) -> tuple[str, ...]:
    if not value:
        return ()
    if not isinstance(value, Mapping) or set(value) - set(EVALUATION):
        raise StudyError(f"invalid value for 'evaluation': {value!r} (allowed: episodes:, every:)")
    return tuple(f"{EVALUATION[k]}={_text(v)}" for k, v in value.items())


def make_grid(block: Mapping[str, Any], defaults: Mapping[str, Any]) -> Grid:
    """One block of the study; a key it does not give is the study's."""
    unknown = sorted(set(block) - set(GRID_KEYS))
    if unknown:
        raise StudyError(f"unknown key {unknown[0]!r} in a grid (allowed: {', '.join(GRID_KEYS)})")
    get = {"algos": ["ppo"], **{k: v for k, v in defaults.items() if v is not None}, **block}.get
    for key in ("tasks", "strategies"):
        if get(key) is None:
            raise StudyError(f"missing key {key!r} (allowed: a study names its tasks and strategies)")
    tasks, task_settings = _tasks(get("tasks"))
    settings = (*_items(get("settings"), "settings"), *_evaluation(get("evaluation")))
    return Grid(
        tasks, task_settings, _algos(get("algos")), _strategies(get("strategies")), settings,
        _steps(get("total_steps")),
    )  # fmt: skip


def comparisons(value: Any, labels: Sequence[str]) -> tuple[Comparison, ...]:
    """``A > B`` claims; a bare label is it against every other. None declared: ``coherent``
    (or else the first strategy listed) against every other."""
    if value is None:
        value = ["coherent" if "coherent" in labels else labels[0]]
    found: list[Comparison] = []
    for item in _names(value, "compare"):
        better, _, than = (p.strip() for p in item.partition(">"))
        pairs = [(better, than)] if than else [(better, o) for o in labels if o != better]
        for a, b in pairs:
            bad = [x for x in (a, b) if x not in labels]
            if bad:
                raise StudyError(f"invalid value for 'compare': {bad[0]!r} (allowed: {', '.join(labels)})")
            found.append(Comparison(a, b))
    return tuple(dict.fromkeys(found))


def make_study(data: Mapping[str, Any], base: Path, default_name: str) -> Study:
    """The study of a file's (or a command line's) declarations; `StudyError` for bad input."""
    unknown = sorted(set(data) - set(FILE_KEYS))
    if unknown:
        raise StudyError(f"unknown key {unknown[0]!r} in the study (allowed: {', '.join(FILE_KEYS)})")
    name = str(data.get("name") or default_name)
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", name):
        raise StudyError(f"invalid value for 'name': {name!r} (allowed: letters, digits, '_', '.', '-')")
    seeds = data.get("seeds", 5)
    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise StudyError(f"invalid value for 'seeds': {seeds!r} (allowed: an integer >= 1)")
    blocks = data.get("grids") or [{}]
    defaults = {k: data.get(k) for k in GRID_KEYS}
    grids = tuple(make_grid(b, defaults) for b in blocks)
    metrics = tuple(_names(data.get("metrics") or ["final", "auc"], "metrics"))
    if set(metrics) - set(METRICS):
        bad = sorted(set(metrics) - set(METRICS))[0]
        raise StudyError(f"invalid value for 'metrics': {bad!r} (allowed: {', '.join(METRICS)})")
    out = (base / str(data.get("out") or Path("studies") / name)).resolve()
    tune = None if data.get("tune") is None else tune_spec.make_tune(data["tune"], _steps)
    study = Study(name, out, base, seeds, grids, metrics, (), tune)
    return dataclasses.replace(study, comparisons=comparisons(data.get("compare"), study.labels()))


def read_file(path: Path) -> dict[str, Any]:
    """A study file's declarations; `StudyError` in one line if it cannot be read."""
    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise StudyError(
            f"invalid study file {str(path)!r}: {exc.strerror} (allowed: a YAML study file)"
        ) from None
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        line = f" at line {where.line + 1}" if where is not None else ""
        raise StudyError(
            f"invalid study file {str(path)!r}: not valid YAML{line} (allowed: a YAML mapping)"
        ) from None
    if not isinstance(data, dict):
        raise StudyError(f"invalid study file {str(path)!r}: {type(data).__name__} (allowed: a YAML mapping)")
    return data


# ------------------------------------------------------------------ checking every cell
@contextlib.contextmanager
def working_dir(path: Path) -> Iterator[None]:
    """Runs the block in `path` (a user's env file is named relative to the study's folder)."""
    before = Path.cwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(before)


def check_pairs(study: Study) -> None:
    """Refuses a strategy its algorithm does not run with, naming the reason and the allowed ones."""
    for grid in study.grids:
        for s in grid.strategies:
            for algo in grid.algos if s.algos is None else s.algos:
                if algo not in strategies.SUPPORTED_ALGOS[s.explore]:
                    why = strategies.REFUSED.get((s.explore, algo), "not supported")
                    raise StudyError(
                        f"invalid pair algo={algo} explore={s.explore} (strategy {s.label!r}): {why} "
                        f"(allowed: algo={', '.join(strategies.SUPPORTED_ALGOS[s.explore])} with it)"
                    )


def check(study: Study, cells: Sequence[Cell]) -> None:
    """Refuses, before anything runs or is written, a bad study: a refused pair, two cells of one
    name, a cell whose sweep would refuse its overrides (each parsed as the sweep will), a bad
    ``tune:`` block (`coherent_jax.study.tune.check`)."""
    check_pairs(study)
    names = [c.name for c in cells]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise StudyError(f"invalid study: cell {twice[0]!r} is declared twice (allowed: distinct labels)")
    if not study.base.is_dir():
        raise StudyError(f"invalid study folder {str(study.base)!r} (allowed: an existing folder)")
    with working_dir(study.base):
        for cell in cells:
            items = [*modern_items(cell.overrides, note=False), f"seeds={cell.seeds}"]
            try:
                parse_sweep(items)
            except ConfigError as exc:
                raise StudyError(f"cell {cell.name!r}: {exc}") from None
        if study.tune is not None:
            tune_spec.check(study.tune, study.cells(tuned=False), study.labels())
