"""The statistics of the report: areas under curves, bootstrap intervals and rliable's
aggregates (IQM, optimality gap, probability of improvement; Agarwal et al. 2021)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from coherent_jax import plot  # noqa: E402

REPS = 2000


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
    from rliable import metrics

    point, low, high = plot.stratified_bootstrap(
        [x, y], lambda a, b: np.array([metrics.probability_of_improvement(a, b)]), reps, seed
    )
    return {"p": float(point[0]), "low": float(low[0]), "high": float(high[0])}


def normalised(scores: dict[str, dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """strategy -> task -> per-seed scores  =>  strategy -> [seeds, tasks], min-max per task.

    Only the tasks every strategy has finished count, so that strategies are compared on
    the same tasks while a suite is incomplete (a task one strategy lacks is left out
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
    from rliable import metrics

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


def first_positive(run) -> float | None:
    """Env steps at which the curve of `run` (a `coherent_jax.plot.Run`) is first above 0, or
    None if it never is (NaN, an iteration that logged nothing, counts as not above)."""
    hits = np.flatnonzero(np.nan_to_num(run.values, nan=0.0) > 0.0)
    return float(run.steps[hits[0]]) if hits.size else None


def reach_summary(runs) -> tuple[int, int, str]:
    """(how many of `runs` ever turned positive, how many runs, the median env step of their
    first positive value as a table shows it, or "-" when none did)."""
    firsts = [first_positive(r) for r in runs]
    hit = [f for f in firsts if f is not None]
    return len(hit), len(firsts), (f"{np.median(hit):,.0f}" if hit else "-")
