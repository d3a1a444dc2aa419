"""Learning curves and aggregate scores: ``python -m coherent_jax.plot RUN_DIR... [out=plots]``.

Each argument is a run directory (``config.yaml`` + ``metrics.jsonl``), a sweep's
directory (its points, ``p003-beta=0.1-seed=1/``, are the runs), or a folder whose
sub-directories are runs and sweeps (such as ``runs/``).

* Runs are averaged only with runs of the same resolved config but for the seed
  (and the settings that do not change what is computed: `NOT_COMPARED`); each such
  group is one line, labelled by the settings in which the groups differ.
* ``learning_curves.png``: one panel per task, one line per group: the mean of
  ``metric`` over seeds against env steps, with a 95% percentile-bootstrap interval
  of that mean as a band (`mean_and_interval`) and the seed count n in the legend.
  A bootstrap interval of a mean never leaves the range of the seeds' values, which
  suits the 2-10 seeds of RL runs (a Student-t interval with n = 2 is 12.7 standard
  errors wide, often far wider than the data). Seeds that logged at different env
  steps are linearly interpolated onto the steps any of them logged within the range
  all of them cover; a group whose runs share no range is drawn run by run.
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
import os
import sys
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from coherent_jax.config import ConfigError, cli, to_dict
from coherent_jax.exit_codes import EXIT_BAD_INPUT
from coherent_jax.run.checkpoint import load_config
from coherent_jax.run.rundir import CONFIG, METRICS, is_sweep, read_metrics, sweep_points

KEYS: dict[str, cli.Key] = {
    "out": cli.Key("plots", cli.output_dir, "a directory that can be written", "where the figures go"),
    "metric": cli.Key("eval/episode_return", cli.text_value, "a metric of metrics.jsonl", "the y axis"),
    "reps": cli.Key(5000, cli.int_at_least(100), "an integer >= 100", "bootstrap resamples"),
    "seed": cli.Key(0, cli.int_at_least(0), "an integer >= 0", "seed of the bootstrap resamples"),
}
# Settings that do not change what a run computes: runs differing only in these
# (and the seed) are seeds of one experiment.
NOT_COMPARED = (
    "seed",
    "run_dir",
    "resume",
    "progress",
    "tensorboard",
    "wandb",
    "wandb_init_timeout",
    "checkpoint_every",
)
# Settings shown as bare values in a label (``ppo coherent``), the others as key=value.
_BARE = ("algo", "explore")


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
    settings: dict[str, Any]  # the flattened resolved config, `NOT_COMPARED` left out


@dataclasses.dataclass
class Curves:
    """One line of a panel: env steps and the seeds' values there, [seeds, steps].

    ``interpolated`` says whether seeds logged at different steps were interpolated;
    ``runs`` are the seeds' runs (drawn one by one when they share no steps: then
    ``steps`` is empty).
    """

    steps: np.ndarray
    values: np.ndarray
    interpolated: bool
    runs: list[Run]


def split_args(argv: Sequence[str]) -> tuple[list[Path], list[str]]:
    """Run directories and ``key=value`` options: an existing path is a directory even
    with ``=`` in its name (a sweep's points), anything else with ``=`` is an option."""
    paths, options = [], []
    for arg in argv:
        if "=" in arg and not Path(arg).exists():
            options.append(arg)
        else:
            paths.append(Path(arg))
    return paths, options


def parse_plot_args(argv: Sequence[str]) -> tuple[list[Path], dict[str, Any]]:
    """Run directories and the settings of `KEYS`; raises `ConfigError` in one line."""
    paths, options = split_args(argv)
    settings = cli.parse_command(options, KEYS, command="plot", config=False).settings
    if not paths:
        raise ConfigError(
            "expected at least one run directory (usage: python -m coherent_jax.plot RUN_DIR...)"
        )
    return paths, settings


def runs_in(path: Path) -> list[Path]:
    """The run directories `path` itself holds: a sweep's points (its root has
    ``grid.json`` beside the shared ``config.yaml``, which is no run), the run it is, or none."""
    if is_sweep(path):
        return sweep_points(path)
    return [path] if (path / CONFIG).is_file() else []


def find_runs(paths: Sequence[Path]) -> list[Path]:
    """The run directories named by `paths`, each a run, a sweep, or a folder of runs and
    sweeps (such as ``runs/``); a run named twice is taken once."""
    runs: list[Path] = []
    for path in paths:
        if not path.is_dir():
            raise ConfigError(f"invalid run directory {str(path)!r}: not a directory")
        found = runs_in(path)
        if not found and not (path / CONFIG).is_file():
            found = [run for child in sorted(path.iterdir()) if child.is_dir() for run in runs_in(child)]
        if not found:
            raise ConfigError(
                f"invalid run directory {str(path)!r}: no {CONFIG} in it or in its sub-directories "
                "(allowed: a training run's directory, a sweep's, or a folder of them)"
            )
        runs.extend(found)
    unique: dict[Path, Path] = {}
    for run in runs:
        unique.setdefault(run.resolve(), run)
    return list(unique.values())


def _flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = tuple(value) if isinstance(value, list) else value
    return flat


def load_run(path: Path, metric: str) -> Run:
    """The curve of `metric` in one run; refuses a run that never logged it."""
    return run_from_rows(path, read_metrics(path / METRICS), metric)


def run_from_rows(path: Path, rows: Sequence[dict[str, Any]], metric: str, source: str = METRICS) -> Run:
    """The curve of `metric` in `rows`, the metrics rows of the run in `path` (whose
    ``config.yaml`` gives its settings) read from `source`; refuses rows that never logged it."""
    cfg = load_config(path)
    rows = [r for r in rows if r.get(metric) is not None]
    if not rows:
        raise ConfigError(
            f"invalid run directory {str(path)!r}: no finite {metric!r} in {source} "
            "(allowed: a run that logged it; metric=train/episode_return plots training returns)"
        )
    steps = np.array([r["env_steps"] for r in rows], dtype=np.int64)
    values = np.array([r[metric] for r in rows], dtype=np.float64)
    order = np.argsort(steps, kind="stable")
    settings = {k: v for k, v in _flatten(to_dict(cfg)).items() if k not in NOT_COMPARED}
    return Run(path, cfg.env, cfg.algo, cfg.explore, cfg.seed, steps[order], values[order], settings)


def labels(runs: Sequence[Run]) -> dict[int, str]:
    """Legend label of each run: the settings in which its group differs from others on its task.

    Runs of one task with equal labels have equal settings but for the seed, so a label
    names one group per task, and the same group on several tasks has the same label
    (the aggregate pairs them). A setting that changes only with the task (a per-task
    hyperparameter such as reward scaling on Hopper alone) is part of the task and
    splits no group, so it is left out. Algorithm and strategy are shown bare (``ppo
    coherent``), other settings as ``key=value``; with one group per task the label is
    the strategy.
    """
    keys = sorted({k for r in runs for k in r.settings} - {"env"})
    envs = {r.env for r in runs}

    def varies_within_a_task(k: str) -> bool:
        return any(len({repr(r.settings.get(k)) for r in runs if r.env == env}) > 1 for env in envs)

    differing = [k for k in keys if varies_within_a_task(k)]
    if not differing:
        return {id(r): r.explore for r in runs}
    ordered = [k for k in _BARE if k in differing] + [k for k in differing if k not in _BARE]

    def label(r: Run) -> str:
        parts = []
        for k in ordered:
            value = r.settings.get(k)
            value = "[" + ",".join(map(str, value)) + "]" if isinstance(value, tuple) else value
            parts.append(str(value) if k in _BARE else f"{k}={value}")
        return " ".join(parts)

    return {id(r): label(r) for r in runs}


def mean_and_interval(
    curves: np.ndarray, reps: int = 5000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over seeds and its 95% percentile-bootstrap interval, curves [n, T].

    Resamples the n seeds with replacement ``reps`` times (the same resamples at
    every step, so the band follows the curves), and takes the 2.5% and 97.5%
    quantiles of the resampled means: (mean, low, high), each [T]. Every resampled
    mean lies between the seeds' smallest and largest value, so the band never
    leaves the data's range (with n = 2 and 3 it is that range); with one seed it is
    the curve itself.
    """
    n = curves.shape[0]
    mean = curves.mean(axis=0)
    if n < 2:
        return mean, mean.copy(), mean.copy()
    idx = np.random.default_rng(seed).integers(0, n, size=(reps, n))
    means = curves[idx].mean(axis=1)  # [reps, T]
    low, high = np.quantile(means, [0.025, 0.975], axis=0)
    return mean, low, high


def common_curves(members: Sequence[Run]) -> Curves:
    """The seeds of one group on shared env steps.

    Where every seed logged the same steps these are exactly the logged values.
    Otherwise the grid is every step any seed logged inside the range all of them
    cover, and each seed is linearly interpolated there (never extrapolated). Seeds
    with no common range give an empty grid; the plot draws them one by one.
    """
    members = sorted(members, key=lambda r: r.seed)
    lo = max(int(r.steps[0]) for r in members)
    hi = min(int(r.steps[-1]) for r in members)
    union = np.unique(np.concatenate([r.steps for r in members]))
    grid = union[(union >= lo) & (union <= hi)]
    if grid.size == 0:
        return Curves(grid, np.zeros((len(members), 0)), False, list(members))
    exact = all(np.array_equal(np.intersect1d(r.steps, grid), grid) for r in members)
    if exact:
        values = np.stack([r.values[np.searchsorted(r.steps, grid)] for r in members])
    else:
        values = np.stack([np.interp(grid, r.steps, r.values) for r in members])
    return Curves(grid, values, not exact, list(members))


def group_curves(runs: Sequence[Run]) -> dict[str, dict[str, Curves]]:
    """task -> label -> that group's `Curves`."""
    label = labels(runs)
    groups: dict[str, dict[str, list[Run]]] = defaultdict(lambda: defaultdict(list))
    for r in runs:
        groups[r.env][label[id(r)]].append(r)
    return {
        env: {name: common_curves(members) for name, members in sorted(by_label.items())}
        for env, by_label in groups.items()
    }


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


def stratified_bootstrap(
    arrays: Sequence[np.ndarray], statistic: Any, reps: int, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """statistic(*arrays) and its 95% percentile interval, each array [runs, tasks]: runs are
    resampled with replacement within each task, independently per array (rliable's
    stratified bootstrap, Agarwal et al. 2021); returns (point, low, high).

    Resampled here with a seeded generator: rliable's `get_interval_estimates` (with
    arch 7.2) gave other intervals on every call from the same RandomState."""
    rng = np.random.default_rng(seed)
    point = np.asarray(statistic(*arrays), np.float64)
    samples = np.empty((reps, *point.shape))
    for r in range(reps):
        resampled = []
        for a in arrays:
            idx = rng.integers(0, a.shape[0], size=a.shape)
            resampled.append(np.take_along_axis(a, idx, axis=0))
        samples[r] = statistic(*resampled)
    low, high = np.percentile(samples, [2.5, 97.5], axis=0)
    return point, low, high


def aggregate_iqm(scores: dict[str, np.ndarray], reps: int, seed: int) -> dict[str, dict[str, float]]:
    """IQM (rliable's metric) of each label's [runs, tasks] scores with a 95% stratified-bootstrap CI."""
    from rliable import metrics  # lazy: slow to import (pandas, arch)

    out = {}
    for k in scores:
        point, low, high = stratified_bootstrap(
            [scores[k]], lambda x: np.array([metrics.aggregate_iqm(x)]), reps, seed
        )
        out[k] = {"iqm": float(point[0]), "ci_low": float(low[0]), "ci_high": float(high[0])}
    return out


def _pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (files only, no display)."""
    import matplotlib  # lazy: slow to import; --help and bad input go without

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: as matplotlib

    return plt


def _save(fig: Any, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    os.replace(tmp, path)


def plot_curves(grouped: dict[str, dict[str, Curves]], metric: str, path: Path, reps: int, seed: int) -> None:
    """One panel per task, one line and band per group (`mean_and_interval`)."""
    plt = _pyplot()
    envs = sorted(grouped)
    fig, axes = plt.subplots(1, len(envs), figsize=(5.0 * len(envs), 3.6), squeeze=False)
    for ax, env in zip(axes[0], envs, strict=True):
        for name, c in grouped[env].items():
            if c.steps.size == 0:  # seeds with no common range of env steps: one line each
                for r in c.runs:
                    ax.plot(r.steps, r.values, linewidth=1.0, label=f"{name} (seed {r.seed}, no overlap)")
                continue
            mean, low, high = mean_and_interval(c.values, reps, seed)
            note = ", interpolated" if c.interpolated else ""
            marker = "o" if c.steps.size == 1 else None
            (line,) = ax.plot(c.steps, mean, marker=marker, label=f"{name} (n={c.values.shape[0]}{note})")
            ax.fill_between(c.steps, low, high, color=line.get_color(), alpha=0.25, linewidth=0)
        ax.set_title(env)
        ax.set_xlabel("env steps")
        ax.set_ylabel(metric)
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    fig.suptitle("mean over seeds and its 95% bootstrap interval", fontsize="small")
    _save(fig, path)
    plt.close(fig)


def plot_aggregate(result: dict[str, dict[str, float]], tasks: Sequence[str], path: Path) -> None:
    plt = _pyplot()
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
    """Writes the figures; returns the exit status (2 for bad input, before anything is written)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help", "help") for a in argv):
        print(__doc__)
        print("options (key=default):", *cli.help_lines(KEYS), sep="\n")
        return 0
    try:
        paths, opts = parse_plot_args(argv)
        runs = [load_run(p, opts["metric"]) for p in find_runs(paths)]
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    out = Path(opts["out"])
    out.mkdir(parents=True, exist_ok=True)
    grouped = group_curves(runs)
    plot_curves(grouped, opts["metric"], out / "learning_curves.png", opts["reps"], opts["seed"])
    print(f"[coherent_jax] {len(runs)} runs, {len(grouped)} task(s): {out / 'learning_curves.png'}")
    for env, by_label in sorted(grouped.items()):
        for name, c in by_label.items():
            if c.steps.size == 0:
                print(
                    f"  {env:<18} {name:<22} n={len(c.runs)}  "
                    "no env steps shared by all seeds: drawn one by one"
                )
                continue
            mean, low, high = mean_and_interval(c.values, opts["reps"], opts["seed"])
            print(
                f"  {env:<18} {name:<22} n={c.values.shape[0]}  {opts['metric']} at {c.steps[-1]} steps: "
                f"{mean[-1]:.2f}, 95% bootstrap CI [{low[-1]:.2f}, {high[-1]:.2f}]"
                + ("  (seeds interpolated onto shared steps)" if c.interpolated else "")
            )
    if len(grouped) >= 2:
        scores, norm = normalized_final_scores(runs)
        if not scores:
            print("[coherent_jax] no group was run on every task: no aggregate", flush=True)
            return 0
        result = aggregate_iqm(scores, opts["reps"], opts["seed"])
        plot_aggregate(result, norm["tasks"], out / "aggregate.png")
        report = {"metric": opts["metric"], "reps": opts["reps"], "seed": opts["seed"], **norm, "iqm": result}
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
