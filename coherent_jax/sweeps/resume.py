"""``python -m coherent_jax.sweep resume=SWEEP_DIR``: the stored grid, and what a resume may restate.

A sweep's grid (its axes and seeds, ``grid.json``) is fixed when it starts: the
checkpoint holds one state per point. A resume may restate it, in part or whole
(the command line that started the sweep, with ``resume=`` added, is accepted), or
leave it out; any change, a list of other values, ``seeds=N`` for another number of
seeds, or one value for a key that is an axis, is refused with "a sweep's grid cannot
change on resume: ...". Every other override is a resume's usual (`runs.resume_config`).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coherent_jax.config import (
    SWEEPABLE,
    Config,
    ConfigError,
    cli,
    get_value,
    parse_overrides,
)
from coherent_jax.config.parse import modern_items, modern_key
from coherent_jax.run import rundir
from coherent_jax.run.runs import METRICS, Checkpoint, load_config, resume_config


def _read_grid(out_dir: Path, pair: tuple[str, str] | None = None) -> tuple[dict[str, list[Any]], list[int]]:
    """(axes, seeds) of ``out_dir/grid.json``; `ConfigError` in one line when it cannot be read.
    `pair`: the sweep's (algo, explore), which names its axes of before."""
    path = Path(out_dir) / rundir.GRID
    try:
        grid = json.loads(path.read_text())
        # A grid stored before the groups names an axis by its flat key (``beta``), one of
        # Coherent-SAC's by psne's (``psne.sigma_init``).
        axes = {modern_key(k, note=False, pair=pair): v for k, v in dict(grid["axes"]).items()}
        seeds = [int(s) for s in grid["seeds"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ConfigError(
            f"invalid value for 'resume': {str(out_dir)!r} has no readable {rundir.GRID} "
            f"({type(exc).__name__}) (allowed: a sweep directory)"
        ) from None
    unknown = [k for k in axes if k not in SWEEPABLE]
    if unknown:
        raise ConfigError(f"invalid {path}: axis {unknown[0]!r} (allowed: {', '.join(SWEEPABLE)})")
    return axes, seeds


def _stored_pair(resume_dir: Path) -> tuple[str, str] | None:
    """The (algo, explore) of the sweep stored in `resume_dir`, or None where it cannot be read
    (refused later, once the directory itself is checked)."""
    try:
        cfg = load_config(resume_dir)
    except ConfigError:
        return None
    return cfg.algo, cfg.explore


def _fmt_list(values: Sequence[Any]) -> str:
    return "[" + ",".join(f"{v:g}" if isinstance(v, float) else str(v) for v in values) + "]"


def _is_grid_item(key: str, text: str, axes: dict[str, list[Any]]) -> bool:
    """Whether an override speaks of the grid: ``seeds=N``, a list of a sweepable key or seed,
    or a value of a key that is one of the sweep's axes."""
    is_list = text.startswith("[") and text.endswith("]")
    return key == "seeds" or (key in ("seed", *SWEEPABLE) and is_list) or key in axes


def _given(key: str, text: str, stored: Config) -> list[Any]:
    """The values a grid item gives, typed as the sweep typed its own (``seeds=N``: the seeds)."""
    if key == "seeds":
        n = cli.parse_value(key, text, cli.Key(None, cli.int_at_least(1), "an integer >= 1", ""))
        return [stored.seed + i for i in range(n)]
    items = [s.strip() for s in text[1:-1].split(",")] if text.startswith("[") else [text]
    if not items or any(not s for s in items):
        raise ConfigError(f"invalid value for {key!r}: {text!r} (allowed: a non-empty list of values)")
    return [get_value(parse_overrides([f"{key}={v}"], base=stored), key) for v in items]


def resume_plan(resume_dir: str, rest: list[str]) -> tuple[Config, Path, dict[str, list[Any]], list[int]]:
    """The stored config, the directory and the grid (axes, seeds) of the sweep to resume.

    `rest` holds the overrides besides ``resume=``; the ones that restate the grid are
    compared with it and dropped, the others go to `runs.resume_config`.
    """
    pair = _stored_pair(Path(resume_dir)) if resume_dir else None
    try:
        stored_axes = _read_grid(Path(resume_dir), pair)[0] if resume_dir else {}
    except ConfigError:
        stored_axes = {}  # not a sweep: refused below, once the directory itself is checked
    rest = [i if i.split("=", 1)[0].strip() == "seeds" else modern_items([i], pair=pair)[0] for i in rest]
    grid_items = [i for i in rest if _is_grid_item(*cli.split_item(i), stored_axes)]
    others = [i for i in rest if i not in grid_items]
    cfg, out_dir = resume_config(resume_dir, others)
    axes, seeds = _read_grid(out_dir, (cfg.algo, cfg.explore))
    for item in grid_items:
        key, text = cli.split_item(item)
        own = seeds if key in ("seed", "seeds") else axes.get(key)
        if _given(key, text, cfg) != own:
            grid = " ".join([*(f"{k}={_fmt_list(v)}" for k, v in axes.items()), f"seed={_fmt_list(seeds)}"])
            raise ConfigError(f"a sweep's grid cannot change on resume: {item} (the sweep's grid: {grid})")
    return cfg, out_dir, axes, seeds


def check_rows(out_dir: Path, point_names: list[str], checkpoint: Checkpoint, finished: bool) -> None:
    """Every point's rows up to the checkpoint must be whole (`rundir.check_metrics`);
    a point that diverged stopped its rows early, so it is not compared."""
    diverged = {int(k) for k in checkpoint.loop.diverged}
    paths = [out_dir / name / METRICS for j, name in enumerate(point_names) if j not in diverged]
    rundir.check_metrics(paths, checkpoint.iteration, finished)
