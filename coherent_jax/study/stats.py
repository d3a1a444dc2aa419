"""The statistics of a study's report: the seeds' curves of a cell, areas under curves,
bootstrap intervals and rliable's aggregates (IQM, optimality gap, probability of
improvement, performance profiles; Agarwal et al. 2021), and when a seed first reached a
sparse reward or a goal. Only the report path loads this module (numpy, rliable)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rliable import metrics

from coherent_jax import plot
from coherent_jax.config import ConfigError
from coherent_jax.study.curves import LOG, METRICS, point_dirs, table_path, table_runs

REPS = 2000
TAUS = np.linspace(0.0, 1.0, 51)  # the performance profiles' thresholds on normalised scores


def load_runs(study_dir: Path, cell: str, metric: str) -> list[plot.Run]:
    """The `coherent_jax.plot.Run` of `metric` of each point of a cell, sorted by point:
    from the point's ``metrics.jsonl`` where it is present, else from the study's table."""
    if metric not in METRICS:
        raise ValueError(f"metric {metric!r} is not in the curves tables (allowed: {', '.join(METRICS)})")
    table = table_path(study_dir)
    runs = []
    for point in point_dirs(Path(study_dir) / cell / "sweep"):
        if (point / LOG).is_file():
            runs.append(plot.load_run(point, metric))
            continue
        rows = table_runs(table).get((cell, point.name))
        if rows is None:
            raise ConfigError(
                f"invalid run directory {str(point)!r}: no {LOG} and no rows in {str(table)!r} "
                "(allowed: a point whose logs are present or in its study's table; experiments/README.md "
                "says where the earlier cells' logs are)"
            )
        runs.append(plot.run_from_rows(point, rows, metric, source=str(table)))
    return runs


def auc(run: plot.Run) -> float:
    """Mean evaluation return over training (trapezoid over env steps)."""
    if run.steps.size < 2:
        return float(run.values[-1])
    return float(np.trapezoid(run.values, run.steps) / (run.steps[-1] - run.steps[0]))


def interval(values: np.ndarray, reps: int = REPS, seed: int = 0) -> tuple[float, float, float]:
    mean, low, high = plot.mean_and_interval(np.asarray(values, np.float64)[:, None], reps, seed)
    return float(mean[0]), float(low[0]), float(high[0])


def probability_of_improvement(
    x: np.ndarray, y: np.ndarray, reps: int = REPS, seed: int = 0
) -> dict[str, float]:
    """P(X > Y) over runs x [n, tasks] and y [m, tasks] (rliable's metric), stratified-bootstrap 95% CI."""
    point, low, high = plot.stratified_bootstrap(
        [x, y], lambda a, b: np.array([metrics.probability_of_improvement(a, b)]), reps, seed
    )
    return {"p": float(point[0]), "low": float(low[0]), "high": float(high[0])}


def normalised(scores: dict[str, dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """strategy -> task -> per-seed scores  =>  strategy -> [seeds, tasks], min-max per task.

    Only the tasks every strategy has finished count, so that strategies are compared on
    the same tasks while a study is incomplete (a task one strategy lacks is left out
    for all; none in common: nothing)."""
    tasks = sorted(set.intersection(*(set(by_task) for by_task in scores.values()))) if scores else []
    if not tasks:
        return {}
    out = {}
    for name, by_task in scores.items():
        by_task = {t: by_task[t] for t in tasks}
        n = min(len(v) for v in by_task.values())
        cols = []
        for t in tasks:
            every = np.concatenate([s[t] for s in scores.values() if t in s])
            lo, hi = float(every.min()), float(every.max())
            cols.append((by_task[t][:n] - lo) / (hi - lo) if hi > lo else np.full(n, 0.5))
        out[name] = np.stack(cols, axis=1)
    return out


def aggregate(norm: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """IQM and optimality gap (rliable's metrics) of each strategy's [runs, tasks] scores, 95% CIs."""
    out = {}
    for k in sorted(norm):
        point, low, high = plot.stratified_bootstrap(
            [norm[k]],
            lambda x: np.array([metrics.aggregate_iqm(x), metrics.aggregate_optimality_gap(x)]),
            REPS,
            0,
        )
        out[k] = {
            "iqm": float(point[0]),
            "iqm_low": float(low[0]),
            "iqm_high": float(high[0]),
            "gap": float(point[1]),
            "gap_low": float(low[1]),
            "gap_high": float(high[1]),
        }
    return out


def performance_profile(scores: np.ndarray, reps: int = REPS, seed: int = 0) -> dict[str, np.ndarray]:
    """The fraction of runs whose normalised score exceeds each threshold of `TAUS` (rliable's
    run-score distribution, averaged over tasks), scores [runs, tasks], with its 95%
    stratified-bootstrap band: {"taus", "profile", "low", "high"}."""

    def profile(x: np.ndarray) -> np.ndarray:
        return (x[None, :, :] > TAUS[:, None, None]).mean(axis=(1, 2))

    point, low, high = plot.stratified_bootstrap([scores], profile, reps, seed)
    return {"taus": TAUS, "profile": point, "low": low, "high": high}


def first_positive(run: plot.Run) -> float | None:
    """Env steps at which the curve of `run` is first above 0, or None if it never is (NaN,
    an iteration that logged nothing, counts as not above)."""
    hits = np.flatnonzero(np.nan_to_num(run.values, nan=0.0) > 0.0)
    return float(run.steps[hits[0]]) if hits.size else None


def reach_summary(runs: list[plot.Run]) -> tuple[int, int, str]:
    """(how many of `runs` ever turned positive, how many runs, the median env step of their
    first positive value as a table shows it, or "-" when none did)."""
    firsts = [first_positive(r) for r in runs]
    hit = [f for f in firsts if f is not None]
    return len(hit), len(firsts), (f"{np.median(hit):,.0f}" if hit else "-")


def improvement_on_task(x: np.ndarray, y: np.ndarray) -> float:
    """P(X > Y) on one task (rliable's metric, ties counting half), x and y one score per seed."""
    return float(metrics.probability_of_improvement(np.asarray(x)[:, None], np.asarray(y)[:, None]))
