"""The figures of a study's report, each with the commit, the CPU and the command at its foot:
learning curves with bootstrap bands, performance profiles with their 95% bands, and the
matrix of probabilities of improvement (claim x task). Drawn on matplotlib's `Figure`
(Agg, files only; no pyplot state), which only the report path loads."""

from __future__ import annotations

import os
import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from coherent_jax import plot

FOOT = 7  # the footer's font size


def _save(fig: Figure, path: Path, footer: str) -> None:
    """Writes `fig` with `footer` (commit, CPU, command) under it, wrapped to its width, atomically."""
    fig.tight_layout()
    width = max(40, int(fig.get_figwidth() * 17))
    text = "\n".join(textwrap.fill(line, width) for line in footer.split("\n"))
    fig.text(0.01, -0.01, text, fontsize=FOOT, color="0.35", ha="left", va="top")
    tmp = path.with_name(path.name + ".tmp")
    fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    os.replace(tmp, path)


def curves(
    by_task: dict[str, dict[str, plot.Curves]], metric: str, path: Path, footer: str, reps: int
) -> None:
    """One panel per task, one line per strategy: the mean over seeds and its 95% bootstrap band
    (`coherent_jax.plot.mean_and_interval`); seeds with no shared env steps drawn one by one."""
    tasks = sorted(by_task)
    fig = Figure(figsize=(5.0 * len(tasks), 4.2))
    axes = fig.subplots(1, len(tasks), squeeze=False)[0]
    for ax, task in zip(axes, tasks, strict=True):
        for label, c in sorted(by_task[task].items()):
            if c.steps.size == 0:
                for r in c.runs:
                    ax.plot(r.steps, r.values, linewidth=1.0, label=f"{label} (seed {r.seed})")
                continue
            mean, low, high = plot.mean_and_interval(c.values, reps, 0)
            marker = "o" if c.steps.size == 1 else None
            (line,) = ax.plot(c.steps, mean, marker=marker, label=f"{label} (n={c.values.shape[0]})")
            ax.fill_between(c.steps, low, high, color=line.get_color(), alpha=0.25, linewidth=0)
        ax.set_title(task)
        ax.set_xlabel("env steps")
        ax.set_ylabel(metric)
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    fig.suptitle("mean over seeds and its 95% bootstrap interval", fontsize="small")
    _save(fig, path, footer)


def profiles(found: dict[str, dict[str, np.ndarray]], tasks: Sequence[str], path: Path, footer: str) -> None:
    """Performance profiles (`coherent_jax.study.stats.performance_profile`): the fraction of
    runs above each normalised score, one line and 95% band per strategy."""
    fig = Figure(figsize=(5.5, 4.2))
    ax = fig.subplots()
    for label, p in sorted(found.items()):
        (line,) = ax.plot(p["taus"], p["profile"], label=label)
        ax.fill_between(p["taus"], p["low"], p["high"], color=line.get_color(), alpha=0.2, linewidth=0)
    ax.set_xlabel("normalised score tau (min-max per task)")
    ax.set_ylabel("fraction of runs with score > tau")
    ax.set_title(f"{len(tasks)} task(s): {', '.join(tasks)}", fontsize="small")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    _save(fig, path, footer)


def matrix(rows: Sequence[str], tasks: Sequence[str], values: np.ndarray, path: Path, footer: str) -> None:
    """P(improvement) of each claim (row) on each task (column) alone, NaN where not run."""
    fig = Figure(figsize=(4.0 + 1.2 * len(tasks), 1.8 + 0.45 * len(rows)))
    ax = fig.subplots()
    image = ax.imshow(np.ma.masked_invalid(values), cmap="RdBu", vmin=0.0, vmax=1.0, aspect="auto")
    ax.set_xticks(range(len(tasks)), tasks, rotation=30, ha="right", fontsize="small")
    ax.set_yticks(range(len(rows)), rows, fontsize="small")
    for (i, j), v in np.ndenumerate(values):
        ax.text(j, i, "-" if np.isnan(v) else f"{v:.2f}", ha="center", va="center", fontsize="small")
    fig.colorbar(image, ax=ax, label="P(improvement)")
    ax.set_title("P(improvement) per task, final return", fontsize="small")
    _save(fig, path, footer)
