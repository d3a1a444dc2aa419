"""The Markdown tables of a study's report, each from the finished cells' runs: the cells
(final return and area under the curve with 95% bootstrap intervals, rate, wall time),
rliable's aggregates per algorithm, the seeds that reached a sparse reward or a goal, and
the verdicts on the claims, with the rule they follow (`verdict`)."""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from coherent_jax import plot
from coherent_jax.study import stats, verify
from coherent_jax.study.cell import Cell, cell_dir

Claim = tuple[str, str, dict[str, float]]  # (what is claimed, its verdict, P(improvement) and CI)
Scores = dict[str, dict[str, dict[str, np.ndarray]]]  # algo -> label -> task -> one value per seed
VERDICT_RULE = (
    "A claim *A > B* holds when the 95% stratified-bootstrap interval of the probability of "
    "improvement P(A > B) (rliable; Agarwal et al. 2021) lies above 0.5, does not hold when it "
    "lies below 0.5, and is inconclusive otherwise. Scores are min-max normalised per task over "
    "both strategies' runs, on the tasks both have finished."
)


def task_of(cell: Cell) -> str:
    """The cell's task as its name gives it (``TASK/ALGO/LABEL``)."""
    return cell.name.split("/", 1)[0]


def verdict(poi: dict[str, float], yes: str = "holds", no: str = "does not hold") -> str:
    """`yes` when the 95% CI of P(improvement) lies above 0.5, `no` when below, else inconclusive."""
    if poi["low"] > 0.5:
        return yes
    if poi["high"] < 0.5:
        return no
    return "inconclusive"


def aggregate_table(
    algo: str, what: str, table: dict[str, dict[str, np.ndarray]], norm, title: str = ""
) -> list[str]:
    """Lines: IQM and optimality gap of every strategy on the tasks all have finished;
    `title` names the group of cells compared (when a report has several)."""
    agg = stats.aggregate(norm)
    common = sorted(set.intersection(*(set(by_task) for by_task in table.values())))
    left_out = sorted({t for by_task in table.values() for t in by_task} - set(common))
    lines = [
        f"**{algo}, {what}{', ' + title if title else ''}**, "
        f"normalised per task over {len(common)} task(s) ({', '.join(common)}"
        + (f"; {', '.join(left_out)} left out until every strategy has finished it" if left_out else "")
        + "):",
        "",
        "| strategy | IQM (95% CI) | optimality gap (95% CI) |",
        "|---|---|---|",
    ]
    for k, v in sorted(agg.items()):
        lines.append(
            f"| {k} | {v['iqm']:.2f} ({v['iqm_low']:.2f}, {v['iqm_high']:.2f}) | "
            f"{v['gap']:.2f} ({v['gap_low']:.2f}, {v['gap_high']:.2f}) |"
        )
    return [*lines, ""]


def cell_table(
    done: Sequence[Cell],
    runs: dict[str, list[plot.Run]],
    study_dirs: dict[str, Path],
    label: Callable[[Cell, plot.Run], str],
    entries: dict,
    own: str,
) -> tuple[list[str], Scores, Scores, list[float]]:
    """The table of cells (seeds, final return and area with 95% CIs, rate, wall time).

    Returns its lines, the final returns and areas per algorithm, `label` and task (one
    value per seed), and the wall times of study `own`'s cells (a cell of another study read
    beside them counts in its own). ``entries``: `verify.load`'s, which mark a cell HEAD no
    longer reproduces bit for bit.
    """
    lines = [
        "| cell | seeds | final return (95% CI) | area under curve (95% CI) | env steps/s | wall |",
        "|---|---|---|---|---|---|",
    ]
    finals: Scores = defaultdict(lambda: defaultdict(dict))
    aucs: Scores = defaultdict(lambda: defaultdict(dict))
    walls: list[float] = []
    for c in done:
        rs = runs[c.name]
        f = np.array([r.values[-1] for r in rs])
        a = np.array([stats.auc(r) for r in rs])
        for name in sorted({label(c, r) for r in rs}):
            keep = [i for i, r in enumerate(rs) if label(c, r) == name]
            finals[c.setting("algo")][name][task_of(c)] = f[keep]
            aucs[c.setting("algo")][name][task_of(c)] = a[keep]
        summary = json.loads((cell_dir(c, study_dirs[c.suite]) / "sweep" / "sweep.json").read_text())
        wall = float(summary.get("wall_s", 0.0))
        walls.append(wall if c.suite == own else 0.0)
        name = (c.name if c.suite == own else f"{c.name} ({c.suite} suite)") + verify.mark(c, entries)
        fm, fl, fh = stats.interval(f)
        am, al, ah = stats.interval(a)
        lines.append(
            f"| {name} | {len(rs)} | {fm:.0f} ({fl:.0f}, {fh:.0f}) | {am:.0f} ({al:.0f}, {ah:.0f}) | "
            f"{summary.get('sweep_env_steps_per_s', float('nan')):.0f} | {wall / 3600:.2f} h |"
        )
    lines += [*verify.footnote(done, entries), ""]
    return lines, finals, aucs, walls


def reach_rows(
    cell: Cell, runs: list[plot.Run], label: Callable[[Cell, plot.Run], str], task: bool
) -> list[str]:
    """Rows, per strategy (`label`) of a cell: the seeds whose curve ever turned positive (a
    sparse reward, a goal reached) and the median env step of the first time; ``task``: with
    the task's column."""
    rows = []
    for name in sorted({label(cell, r) for r in runs}):
        hit, n, first = stats.reach_summary([r for r in runs if label(cell, r) == name])
        lead = f"| {task_of(cell)} " if task else ""
        rows.append(f"{lead}| {name} | {hit} of {n} | {first} |")
    return rows


def verdict_lines(claims: list[Claim], rule: str = VERDICT_RULE) -> list[str]:
    """The verdicts table (empty without claims), after the rule it follows."""
    if not claims:
        return []
    lines = ["## Verdicts", "", rule, "", "| claim | P(improvement) (95% CI) | verdict |", "|---|---|---|"]
    lines += [f"| {c} | {p['p']:.2f} ({p['low']:.2f}, {p['high']:.2f}) | {v} |" for c, v, p in claims]
    lines.append("")
    return lines


def claim(
    better: str,
    than: str,
    per_label: dict[str, dict[str, np.ndarray]],
    what: str,
    yes_no=("holds", "does not hold"),
) -> Claim | None:
    """The claim ``better > than`` on the tasks both have finished (None if none), judged."""
    pair = stats.normalised({better: per_label[better], than: per_label[than]})
    if not pair:
        return None
    poi = stats.probability_of_improvement(pair[better], pair[than])
    tasks = pair[better].shape[1]
    return f"{what}: {better} improves on {than} ({tasks} task(s))", verdict(poi, *yes_no), poi
