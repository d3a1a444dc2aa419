"""A sweep's grid: ``python -m coherent_jax.sweep explore=coherent seeds=8 coherent.beta=[0,0.01,0.1,1]``.

Every ``key=value`` of ``python -m coherent_jax.train`` is accepted; a sweepable key
(declared on its config field, `config.Sweepable`; or ``seed``) given a list,
``coherent.beta=[0,0.01,0.1,1]``, becomes an axis of the grid, and ``seeds=N`` runs each
point with seeds ``seed, seed+1, ..., seed+N-1``. The grid is the product of the axes
(seeds innermost): `parse_sweep` reads it into a `SweepPlan` of `Point`s. A bad key or
value (an unknown key, a list for a shape setting, an empty list, a value out of range,
an axis the algorithm does not read) is a `ConfigError` naming it, before anything is
written.

``resume=SWEEP_DIR`` (`read_sweep`, `resume_plan`): a sweep's grid (its axes and seeds,
``grid.json``) is fixed when it starts: the checkpoint holds one state per point. A
resume may restate it, in part or whole (the command line that started the sweep, with
``resume=`` added, is accepted), or leave it out; any change, a list of other values,
``seeds=N`` for another number of seeds, or one value for a key that is an axis, is
refused with "a sweep's grid cannot change on resume: ...". Every other override is a
resume's usual (`checkpoint.resume_config`).

The aggregate over seeds of the final evaluation return per non-seed point (`aggregate`)
is written as ``sweep.csv`` (`to_csv`) and printed (`format_table`). The grid runs as
one vmapped program, `coherent_jax.run.training.run_sweep`; the command's launch path is
`coherent_jax.run.launch.launch_sweep`. No JAX here.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import itertools
import json
import statistics
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coherent_jax.config import (
    FIELDS,
    SWEEPABLE,
    Config,
    ConfigError,
    cli,
    get_value,
    parse_overrides,
    sweepable,
    validate,
    with_values,
)
from coherent_jax.config.parse import modern_items, modern_key
from coherent_jax.config.schema import MAX_SEED
from coherent_jax.run import rundir
from coherent_jax.run.checkpoint import Checkpoint, load_config, resume_config, split_resume
from coherent_jax.run.rundir import METRICS

# Keys that may take a list of values: the state's array hyperparameters, and seed.
AXIS_KEYS = (*SWEEPABLE, "seed")
# The sweep's own keys (everything else is a training-config key or an axis).
SWEEP_KEYS = {
    "seeds": cli.Key(
        default=None,
        parse=cli.int_at_least(1),
        allowed="an integer >= 1",
        help="runs every point with seeds seed, seed+1, ..., seed+N-1 (default: seed alone)",
    ),
}


@dataclasses.dataclass(frozen=True)
class Point:
    """One grid point: its settings along the non-seed axes, its seed and its config."""

    index: int
    values: dict[str, Any]
    seed: int
    cfg: Config

    @property
    def name(self) -> str:
        # A group's key by its last part (``beta=0.1``): the names sweeps have always had.
        parts = [f"{k.rsplit('.', 1)[-1]}={fmt(v)}" for k, v in self.values.items()]
        return "-".join([f"p{self.index:03d}", *parts, f"seed={self.seed}"])


@dataclasses.dataclass(frozen=True)
class SweepPlan:
    """The validated grid: the shared config, the axes in the order given, the seeds, the points."""

    base: Config
    axes: dict[str, list[Any]]
    seeds: list[int]
    points: list[Point]


def _is_list(text: str) -> bool:
    return text.startswith("[") and text.endswith("]")


def _list_items(key: str, text: str) -> list[str]:
    items = [s.strip() for s in text[1:-1].split(",")]
    if items == [""] or any(not s for s in items):
        raise ConfigError(
            f"invalid value for {key!r}: {text!r} (allowed: a non-empty list of values, e.g. [0.01,0.1])"
        )
    return items


def parse_sweep(argv: Sequence[str]) -> SweepPlan:
    """Splits ``key=value`` strings into the grid; raises `ConfigError` naming the bad key or value.

    The axes (a sweepable key or ``seed`` given a list) are taken out first; the rest,
    the sweep's own keys (`SWEEP_KEYS`) and single training-config values, go through
    the command-line parser shared by every entry point (`coherent_jax.config.cli`).
    """
    fields = FIELDS
    scalars: list[str] = []
    axes: dict[str, list[str]] = {}
    for item in modern_items(argv):
        key, text = cli.split_item(item)
        list_field = key in fields and "list" in str(fields[key].type)
        # policy_hidden=[64,64] is one value of a list setting; [[8],[16]] would be an axis of them.
        if key in fields and _is_list(text) and (not list_field or text.startswith("[[")):
            if key not in AXIS_KEYS:
                raise ConfigError(
                    f"invalid value for {key!r}: {text!r} (allowed: one value; it sets shapes or the "
                    f"program, so it cannot vary within a sweep; keys that take a list: "
                    f"{', '.join(AXIS_KEYS)})"
                )
            axes[key] = _list_items(key, text)
        else:
            scalars.append(item)
    parsed = cli.parse_command(scalars, SWEEP_KEYS, command="sweep")
    base, num_seeds, scalars = parsed.config, parsed.settings["seeds"], parsed.config_items
    seed_items = axes.pop("seed", None)
    if seed_items is not None and num_seeds is not None:
        raise ConfigError(
            f"invalid key 'seeds': {num_seeds} with seed={seed_items} "
            "(allowed: either seeds=N or a list of seeds)"
        )
    for key in axes:
        if not sweepable(key).read_by(base.algo, base.explore):
            raise ConfigError(
                f"invalid key {key!r}: algo={base.algo} explore={base.explore} does not use it "
                f"(allowed: keys that change its hyperparameters)"
            )
    # Each value parsed as a single override would be (typed, and checked: e.g. beta=2).
    typed = {
        k: [get_value(parse_overrides([*scalars, f"{k}={v}"]), k) for v in items] for k, items in axes.items()
    }
    if seed_items is None:
        seeds = [base.seed + i for i in range(num_seeds or 1)]
        if seeds[-1] > MAX_SEED:
            raise ConfigError(
                f"invalid value for 'seeds': {num_seeds} with seed={base.seed} (allowed: at most "
                f"{MAX_SEED - base.seed + 1}, so that seed + seeds - 1 <= {MAX_SEED}: "
                "the PRNG key is derived from the seed's 32 bits)"
            )
    else:
        seeds = [parse_overrides([*scalars, f"seed={v}"]).seed for v in seed_items]
    return make_plan(base, typed, seeds)


def make_plan(base: Config, axes: dict[str, list[Any]], seeds: list[int]) -> SweepPlan:
    """The grid of `axes` x `seeds` over `base` (seeds innermost), each point's config validated."""
    points: list[Point] = []
    for combo in itertools.product(*axes.values(), seeds):
        *values, seed = combo
        settings = dict(zip(axes, values, strict=True))
        cfg = validate(with_values(base, {**settings, "seed": seed}))
        points.append(Point(index=len(points), values=settings, seed=seed, cfg=cfg))
    return SweepPlan(base=base, axes={k: list(v) for k, v in axes.items()}, seeds=list(seeds), points=points)


def read_sweep(argv: Sequence[str]) -> tuple[SweepPlan, Path | None]:
    """The plan of `argv` and, for ``resume=SWEEP_DIR``, the sweep's directory (its stored
    config and grid, which the items may restate but not change); raises `ConfigError`."""
    resume_dir, rest = split_resume(list(argv))
    cli.check_unique(list(argv))
    if resume_dir is None:
        return parse_sweep(argv), None
    cfg, out_dir, axes, seeds = resume_plan(resume_dir, rest)
    return make_plan(cfg, axes, seeds), out_dir


# --- resume=SWEEP_DIR -----------------------------------------------------------------------------


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
    compared with it and dropped, the others go to `checkpoint.resume_config`.
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


# --- the aggregate over seeds ---------------------------------------------------------------------


def fmt(value: Any) -> str:
    """A grid value as names and tables show it (floats in ``%g``)."""
    return f"{value:g}" if isinstance(value, float) else str(value)


def aggregate(plan: Any, summaries: list[dict]) -> list[dict]:
    """Mean and sample standard deviation (ddof 1; None with fewer than two finite
    returns) over seeds of the final eval return, per non-seed point."""
    groups: dict[tuple, list[dict]] = {}
    for s in summaries:
        groups.setdefault(tuple(s[k] for k in plan.axes), []).append(s)
    rows = []
    for values, members in groups.items():
        returns = [m["final_eval_return"] for m in members if m["final_eval_return"] is not None]
        rows.append(
            {
                **dict(zip(plan.axes, values, strict=True)),
                "seeds": len(members),
                "final_eval_return_mean": statistics.fmean(returns) if returns else None,
                "final_eval_return_std": statistics.stdev(returns) if len(returns) > 1 else None,
                "non_finite": len(members) - len(returns),
            }
        )
    return rows


def to_csv(plan: Any, rows: list[dict]) -> str:
    """`aggregate`'s rows as ``sweep.csv``: the axes, the seed count, mean and std, non-finite seeds."""
    buf = io.StringIO()
    columns = [*plan.axes, "seeds", "final_eval_return_mean", "final_eval_return_std", "non_finite"]
    writer = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def format_table(plan: Any, rows: list[dict]) -> str:
    """`aggregate`'s rows as the table a finished sweep prints: mean ± sample sd over the
    n seeds with a finite return (`summary_text`)."""
    header = (
        "".join(f"{k:>12}" for k in plan.axes)
        + f"{'seeds':>7}  final eval return, mean ± sd (sample sd over the n finite seeds)"
    )
    lines = [header]
    for r in rows:
        value = summary_text(
            r["final_eval_return_mean"], r["final_eval_return_std"], r["seeds"] - r["non_finite"]
        )
        lines.append("".join(f"{fmt(r[k]):>12}" for k in plan.axes) + f"{r['seeds']:>7}  {value}")
    return "\n".join(lines)


def summary_text(mean: float | None, sd: float | None, n: int) -> str:
    """``92.6 ± 26.6 (n=2)``: a mean, its sample sd and the count; one value has no sd."""
    if mean is None:
        return "non-finite"
    if sd is None:
        return f"{mean:10.1f} (n={n})"
    return f"{mean:10.1f} ± {sd:.1f} (n={n})"
