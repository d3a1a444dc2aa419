"""Learning curves and aggregate scores: ``python -m coherent_jax.plot RUN_DIR... [out=plots]``.

Each argument is a run directory (``config.yaml`` + ``metrics.jsonl``) or a folder
whose sub-directories are runs. Runs are grouped by task and, within a task, by
exploration strategy (with the algorithm in the label when a task has several).

* ``learning_curves.png``: one panel per task, one line per strategy: the mean of
  ``metric`` over seeds against env steps, and a 95% Student-t interval
  ``mean +- t_{0.975, n-1} s / sqrt(n)`` (n seeds, s their sample std) as a band.
* With two or more tasks, ``aggregate.png`` and ``aggregate.json``: the interquartile
  mean (IQM) of normalised final scores across all runs and tasks, with 95%
  stratified-bootstrap confidence intervals (Agarwal et al. 2021, computed with
  ``rliable``). A run's final score is its last value of ``metric``; each task's
  scores are min-max normalised over all runs of that task, so 0 is the worst and
  1 the best final score seen on it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from coherent_jax.config import ConfigError
from coherent_jax.runs import CONFIG, METRICS, load_config, read_metrics

EXIT_BAD_INPUT = 2


@dataclasses.dataclass
class PlotConfig:
    """Options of ``python -m coherent_jax.plot RUN_DIR... [key=value ...]``."""

    out: str = "plots"
    metric: str = "eval/episode_return"
    reps: int = 5000
    seed: int = 0


@dataclasses.dataclass
class Run:
    """One run's curve: env steps and the metric's values where it was logged."""

    path: Path
    env: str
    algo: str
    explore: str
    seed: int
    steps: np.ndarray
    values: np.ndarray


def parse_plot_args(argv: Sequence[str]) -> tuple[list[Path], PlotConfig]:
    """Run directories then ``key=value`` options; raises `ConfigError` in one line."""
    paths = [Path(a) for a in argv if "=" not in a]
    options = [a for a in argv if "=" in a]
    if not paths:
        raise ConfigError(
            "expected at least one run directory (usage: python -m coherent_jax.plot RUN_DIR...)"
        )
    known = {f.name: f for f in dataclasses.fields(PlotConfig)}
    values: dict[str, Any] = {}
    for item in options:
        key, value = (s.strip() for s in item.split("=", 1))
        if key not in known:
            raise ConfigError(f"unknown key {key!r}; valid keys: {', '.join(sorted(known))}")
        if known[key].type in ("int", int):
            try:
                values[key] = int(value)
            except ValueError:
                raise ConfigError(f"invalid value for {key!r}: {value!r} (allowed: an integer)") from None
        else:
            values[key] = value
    opts = PlotConfig(**values)
    if opts.reps < 100:
        raise ConfigError(f"invalid value for 'reps': {opts.reps} (allowed: an integer >= 100)")
    if opts.seed < 0:
        raise ConfigError(f"invalid value for 'seed': {opts.seed} (allowed: an integer >= 0)")
    return paths, opts


def find_runs(paths: Sequence[Path]) -> list[Path]:
    """The run directories named by `paths` (each a run or a folder of runs)."""
    runs: list[Path] = []
    for path in paths:
        if not path.is_dir():
            raise ConfigError(f"invalid run directory {str(path)!r}: not a directory")
        if (path / CONFIG).is_file():
            runs.append(path)
            continue
        inner = sorted(p for p in path.iterdir() if (p / CONFIG).is_file())
        if not inner:
            raise ConfigError(
                f"invalid run directory {str(path)!r}: no {CONFIG} in it or in its sub-directories "
                "(allowed: a training run's directory or a folder of them)"
            )
        runs.extend(inner)
    return runs


def load_run(path: Path, metric: str) -> Run:
    """The curve of `metric` in one run; refuses a run that never logged it."""
    cfg = load_config(path)
    rows = [r for r in read_metrics(path / METRICS) if r.get(metric) is not None]
    if not rows:
        raise ConfigError(
            f"invalid run directory {str(path)!r}: no finite {metric!r} in {METRICS} "
            "(allowed: a run that logged it; metric=train/episode_return plots training returns)"
        )
    steps = np.array([r["env_steps"] for r in rows], dtype=np.int64)
    values = np.array([r[metric] for r in rows], dtype=np.float64)
    return Run(path, cfg.env, cfg.algo, cfg.explore, cfg.seed, steps, values)


def labels(runs: Sequence[Run]) -> dict[int, str]:
    """Legend label of each run: its strategy, with the algorithm if a task has several."""
    algos: dict[str, set[str]] = defaultdict(set)
    for r in runs:
        algos[r.env].add(r.algo)
    return {id(r): (f"{r.algo} {r.explore}" if len(algos[r.env]) > 1 else r.explore) for r in runs}


def mean_and_interval(curves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean over seeds and the half-width of the 95% Student-t interval, curves [n, T].

    ``t_{0.975, n-1} * s / sqrt(n)`` with s the sample std (ddof 1); 0 for one seed.
    """
    from scipy import stats

    n = curves.shape[0]
    mean = curves.mean(axis=0)
    if n < 2:
        return mean, np.zeros_like(mean)
    half = stats.t.ppf(0.975, n - 1) * curves.std(axis=0, ddof=1) / math.sqrt(n)
    return mean, half


def group_curves(runs: Sequence[Run]) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """task -> label -> (env steps logged by every seed, curves [seeds, steps])."""
    label = labels(runs)
    groups: dict[str, dict[str, list[Run]]] = defaultdict(lambda: defaultdict(list))
    for r in runs:
        groups[r.env][label[id(r)]].append(r)
    out: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    for env, by_label in groups.items():
        out[env] = {}
        for name, members in sorted(by_label.items()):
            common = members[0].steps
            for r in members[1:]:
                common = np.intersect1d(common, r.steps)
            curves = np.stack([r.values[np.searchsorted(r.steps, common)] for r in members])
            out[env][name] = (common, curves)
    return out


def normalized_final_scores(runs: Sequence[Run]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """label -> scores [seeds, tasks] (min-max normalised per task), and the bounds used.

    Tasks are in sorted order; a label needs a run on every task, and uses as many
    seeds per task as its task with the fewest (the lowest seeds).
    """
    label = labels(runs)
    tasks = sorted({r.env for r in runs})
    bounds = {}
    for env in tasks:
        finals = [r.values[-1] for r in runs if r.env == env]
        bounds[env] = (float(min(finals)), float(max(finals)))
    per: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in sorted(runs, key=lambda r: r.seed):
        lo, hi = bounds[r.env]
        per[label[id(r)]][r.env].append((r.values[-1] - lo) / (hi - lo) if hi > lo else 0.5)
    scores = {}
    for name, by_task in sorted(per.items()):
        if set(by_task) != set(tasks):
            continue
        n = min(len(v) for v in by_task.values())
        scores[name] = np.array([[by_task[env][i] for env in tasks] for i in range(n)])
    return scores, {"tasks": tasks, "bounds": bounds}


def aggregate_iqm(scores: dict[str, np.ndarray], reps: int, seed: int) -> dict[str, dict[str, float]]:
    """IQM of each label's [runs, tasks] scores with a 95% stratified-bootstrap CI (rliable)."""
    from rliable import library as rly
    from rliable import metrics

    point, interval = rly.get_interval_estimates(
        scores,
        lambda x: np.array([metrics.aggregate_iqm(x)]),
        reps=reps,
        confidence_interval_size=0.95,
        random_state=np.random.RandomState(seed),
    )
    return {
        k: {
            "iqm": float(point[k][0]),
            "ci_low": float(interval[k][0, 0]),
            "ci_high": float(interval[k][1, 0]),
        }
        for k in scores
    }


def _save(fig: Any, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    os.replace(tmp, path)


def plot_curves(
    grouped: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]], metric: str, path: Path
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    envs = sorted(grouped)
    fig, axes = plt.subplots(1, len(envs), figsize=(5.0 * len(envs), 3.6), squeeze=False)
    for ax, env in zip(axes[0], envs, strict=True):
        for name, (steps, curves) in grouped[env].items():
            mean, half = mean_and_interval(curves)
            (line,) = ax.plot(steps, mean, label=f"{name} (n={curves.shape[0]})")
            ax.fill_between(steps, mean - half, mean + half, color=line.get_color(), alpha=0.25, linewidth=0)
        ax.set_title(env)
        ax.set_xlabel("env steps")
        ax.set_ylabel(metric)
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    fig.suptitle("mean and 95% t-interval over seeds", fontsize="small")
    _save(fig, path)
    plt.close(fig)


def plot_aggregate(result: dict[str, dict[str, float]], tasks: Sequence[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted(result)
    fig, ax = plt.subplots(figsize=(5.0, 0.6 + 0.5 * len(names)))
    for y, name in enumerate(names):
        r = result[name]
        ax.plot([r["ci_low"], r["ci_high"]], [y, y], linewidth=8, alpha=0.4, solid_capstyle="butt")
        ax.plot([r["iqm"]], [y], marker="|", markersize=16, color="black")
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("IQM of min-max normalised final score (95% stratified bootstrap CI)")
    ax.set_title(f"{len(tasks)} tasks: {', '.join(tasks)}", fontsize="small")
    ax.grid(axis="x", alpha=0.3)
    _save(fig, path)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "help") for a in argv):
        print(__doc__)
        return 0
    try:
        paths, opts = parse_plot_args(argv)
        runs = [load_run(p, opts.metric) for p in find_runs(paths)]
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    out = Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    grouped = group_curves(runs)
    plot_curves(grouped, opts.metric, out / "learning_curves.png")
    print(f"[coherent_jax] {len(runs)} runs, {len(grouped)} task(s): {out / 'learning_curves.png'}")
    for env, by_label in sorted(grouped.items()):
        for name, (steps, curves) in by_label.items():
            mean, half = mean_and_interval(curves)
            print(
                f"  {env:<18} {name:<22} n={curves.shape[0]}  final {opts.metric} at {steps[-1]} steps: "
                f"{mean[-1]:.2f} +- {half[-1]:.2f}"
            )
    if len(grouped) >= 2:
        scores, norm = normalized_final_scores(runs)
        if not scores:
            print("[coherent_jax] no strategy was run on every task: no aggregate", flush=True)
            return 0
        result = aggregate_iqm(scores, opts.reps, opts.seed)
        plot_aggregate(result, norm["tasks"], out / "aggregate.png")
        report = {"metric": opts.metric, "reps": opts.reps, "seed": opts.seed, **norm, "iqm": result}
        tmp = out / "aggregate.json.tmp"
        tmp.write_text(json.dumps(report, indent=2))
        os.replace(tmp, out / "aggregate.json")
        for name, r in result.items():
            print(
                f"  aggregate IQM {name:<22} {r['iqm']:.3f}  95% CI [{r['ci_low']:.3f}, {r['ci_high']:.3f}]"
            )
        print(f"[coherent_jax] {out / 'aggregate.png'}, {out / 'aggregate.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
