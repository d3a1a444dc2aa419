"""A study's report: ``python -m coherent_jax.study report DIR`` writes ``DIR/REPORT.md`` and
its figures (``DIR/figures/``) from the study's finished cells (``DIR/study.json`` names
them, with the metrics and the claims declared):

* the cells: per cell the mean final evaluation return over seeds and the area under the
  curve (mean evaluation return over training), each with its 95% bootstrap interval, the
  rate and the wall time; the commits and CPUs the numbers came from;
* learning curves per algorithm, one panel per task: the mean over seeds and its 95%
  bootstrap band;
* with ``reach`` among the metrics: per strategy the seeds that ever reached a sparse reward
  or a goal (a training episode with a positive return, or ``train/goal_reached``) and the
  median env step of the first time;
* rliable's aggregates per algorithm (Agarwal et al. 2021): scores min-max normalised per
  task, IQM and optimality gap with 95% stratified-bootstrap intervals, performance profiles;
* with a ``tune:`` block, the tuning: its protocol, the budget each strategy spent, the values
  chosen and every candidate's score, the tuning and evaluation seeds (`coherent_jax.study.tune_run`);
* a verdict per declared claim (``compare``): holds, does not hold or inconclusive, by the
  rule `coherent_jax.study.tables.VERDICT_RULE` states; and the probability of improvement of
  each claim on each task alone, as one matrix (claim x task).

Every figure carries the commit, the CPU and the command at its foot. Cells not finished are
listed, never silently left out. Bad input (a folder holding no study) is one line and exit
status 2.
"""

from __future__ import annotations

import json
import re
import sys
import time
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from coherent_jax import plot
from coherent_jax.config import ConfigError
from coherent_jax.exit_codes import EXIT_BAD_INPUT
from coherent_jax.run.rundir import cpu_info, git_state
from coherent_jax.study import figures, stats, tables, tune_run, verify
from coherent_jax.study.cell import Cell, StudyError, cell_state
from coherent_jax.study.curves import EVAL, TRAIN, TRAIN_GOAL
from coherent_jax.study.execute import RECORD

REPORT = "REPORT.md"
FIGURES = "figures"
WHAT = {"final": "final return", "auc": "area under curve"}


def read_record(study_dir: Path) -> dict[str, Any]:
    """The study's ``study.json``; `StudyError` for a folder that holds no study."""
    path = Path(study_dir) / RECORD
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        raise StudyError(
            f"invalid study folder {str(study_dir)!r}: no readable {RECORD} "
            "(allowed: the folder a study ran in, out=)"
        ) from None


def point_label(cell: Cell, run: plot.Run) -> str:
    """A run's strategy label: the cell's, and a grid point's settings (``coherent[beta=0.1]``)."""
    point = re.sub(r"^p\d+-?|-?seed=-?\d+$", "", run.path.name)
    return f"{cell.label}[{point}]" if point else cell.label


def footer(record: dict[str, Any], done: Sequence[Cell], study_dir: Path) -> str:
    """The figures' foot: where the numbers came from and the command."""
    commits, cpus = set(), set()
    for c in done:
        try:
            v = json.loads((study_dir / c.name / "sweep" / "versions.json").read_text())
        except (OSError, ValueError):
            continue
        commits.add((v.get("git_commit") or "no commit")[:12])
        cpus.add(v.get("cpu_model") or "unknown CPU")
    made = f"cells at commit {', '.join(sorted(commits)) or 'unknown'} on {', '.join(sorted(cpus)) or '?'}"
    here = f"report at {(git_state()['git_commit'] or 'no commit')[:12]} on {cpu_info()['cpu_model']}"
    return f"{made}; {here}\n{record['command']}"


def _curves(
    done: Sequence[Cell], runs: dict[str, list[plot.Run]]
) -> dict[str, dict[str, dict[str, plot.Curves]]]:
    """algo -> task -> label -> the seeds' curves on shared env steps."""
    grouped: dict[str, dict[str, dict[str, list[plot.Run]]]] = defaultdict(lambda: defaultdict(dict))
    for c in done:
        for r in runs[c.name]:
            grouped[c.setting("algo")][tables.task_of(c)].setdefault(point_label(c, r), []).append(r)
    return {
        a: {t: {k: plot.common_curves(v) for k, v in by.items()} for t, by in ts.items()}
        for a, ts in grouped.items()
    }


def reach_lines(done: Sequence[Cell], study_dir: Path) -> list[str]:
    """The seeds that ever reached a goal (``train/goal_reached``) or a sparse reward."""
    lines = [
        "## Reach",
        "",
        "Seeds whose exploration ever reached the goal (a training episode that reached it, where the",
        "task logs `train/goal_reached`) or a sparse reward (a training episode with a positive return),",
        "and the median env step of the first time.",
        "",
        "| task | strategy | seeds that reached it | first reached at (median env steps) |",
        "|---|---|---|---|",
    ]
    for c in done:
        try:
            runs = stats.load_runs(study_dir, c.name, TRAIN_GOAL)
        except ConfigError:  # the task logs no goal: its reward
            runs = stats.load_runs(study_dir, c.name, TRAIN)
        lines += tables.reach_rows(c, runs, point_label, task=True)
    return [*lines, ""]


def _matching(label: str, per_label: dict[str, Any]) -> list[str]:
    return [k for k in per_label if k == label or k.startswith(f"{label}[")]


def judged(record: dict[str, Any], scores: dict[str, tables.Scores]) -> tuple[list[tables.Claim], list]:
    """Every declared claim per algorithm and metric, judged; and the matrix rows (name, algo, A, B)."""
    claims, rows = [], []
    algos = sorted(scores["final"])
    for item in record["compare"]:
        better, than = (x.strip() for x in item.split(">"))
        for algo in algos:
            for metric in [m for m in record["metrics"] if m in WHAT]:
                per_label = scores[metric][algo]
                for a in _matching(better, per_label):
                    for b in _matching(than, per_label):
                        found = tables.claim(a, b, per_label, f"{algo}, {WHAT[metric]}")
                        if found:
                            claims.append(found)
                        if metric == "final" and (a, b, algo) not in {(r[2], r[3], r[1]) for r in rows}:
                            name = f"{a} > {b}" + (f" ({algo})" if len(algos) > 1 else "")
                            rows.append((name, algo, a, b))
    return claims, rows


def matrix_values(rows: list, finals: tables.Scores) -> tuple[list[str], np.ndarray]:
    """P(A > B) on each task alone (NaN where either has not finished it)."""
    tasks = sorted({t for by in finals.values() for per in by.values() for t in per})
    values = np.full((len(rows), len(tasks)), np.nan)
    for i, (_, algo, a, b) in enumerate(rows):
        for j, t in enumerate(tasks):
            x, y = finals[algo].get(a, {}).get(t), finals[algo].get(b, {}).get(t)
            if x is not None and y is not None:
                values[i, j] = stats.improvement_on_task(x, y)
    return tasks, values


def aggregate_lines(
    scores: dict[str, tables.Scores], metrics: Sequence[str], figs: Path, foot: str
) -> list[str]:
    """Per algorithm and metric: IQM and optimality gap; performance profiles of the final return."""
    lines = ["## Aggregates", ""]
    for algo in sorted(scores["final"]):
        for metric in [m for m in metrics if m in WHAT]:
            per_label = scores[metric][algo]
            norm = stats.normalised(per_label)
            if len(norm) < 2:
                continue
            lines += tables.aggregate_table(algo, WHAT[metric], per_label, norm)
            if metric == "final":
                path = figs / f"profile-{algo}.png"
                found = {k: stats.performance_profile(v) for k, v in norm.items()}
                tasks = sorted(set.intersection(*(set(t) for t in per_label.values())))
                figures.profiles(found, tasks, path, foot)
                lines += [f"![performance profiles, {algo}]({FIGURES}/{path.name})", ""]
    return lines


def build(study_dir: Path, record: dict[str, Any]) -> str:
    """REPORT.md's text (its figures written beside it)."""
    cells = [Cell(s["suite"], s["name"], tuple(s["overrides"]), int(s["seeds"])) for s in record["cells"]]
    done = [c for c in cells if cell_state(c, study_dir) == "done"]
    runs = {c.name: stats.load_runs(study_dir, c.name, EVAL) for c in done}
    figs = study_dir / FIGURES
    figs.mkdir(exist_ok=True)
    foot = footer(record, done, study_dir)
    lines = [f"# Study `{record['name']}`", "", f"`{record['command']}`", "", foot.split("\n")[0] + ".", ""]
    lines += [f"Generated {time.strftime('%Y-%m-%d')} by `python -m coherent_jax.study report`.", ""]
    if record.get("tune"):
        lines += tune_run.report_lines(study_dir)
    lines += ["## Cells", ""]
    table, finals, aucs, _ = tables.cell_table(
        done, runs, {record["name"]: study_dir}, point_label, verify.load(study_dir), record["name"]
    )
    lines += [*table, *verify.provenance_lines(done, {record["name"]: study_dir})]
    lines += ["## Learning curves", ""]
    for algo, by_task in sorted(_curves(done, runs).items()):
        path = figs / f"curves-{algo}.png"
        figures.curves(by_task, EVAL, path, foot, stats.REPS)
        lines += [f"![learning curves, {algo}]({FIGURES}/{path.name})", ""]
    if "reach" in record["metrics"]:
        lines += reach_lines(done, study_dir)
    scores = {"final": finals, "auc": aucs}
    lines += aggregate_lines(scores, record["metrics"], figs, foot)
    claims, rows = judged(record, scores)
    lines += tables.verdict_lines(claims)
    if rows:
        tasks, values = matrix_values(rows, finals)
        figures.matrix([r[0] for r in rows], tasks, values, figs / "improvement.png", foot)
        lines += [f"![probability of improvement per task]({FIGURES}/improvement.png)", ""]
    missing = [f"- {c.name} ({cell_state(c, study_dir)})" for c in cells if c not in done]
    if missing:
        lines += ["## Cells not finished", "", *missing, ""]
    return "\n".join(lines)


def main(argv: Sequence[str]) -> int:
    """``report DIR``: writes DIR/REPORT.md; 2 for a folder that holds no study."""
    if len(argv) != 1:
        print("error: invalid arguments (allowed: report DIR, the folder a study ran in)", file=sys.stderr)
        return EXIT_BAD_INPUT
    study_dir = Path(argv[0]).absolute()
    try:
        record = read_record(study_dir)
    except StudyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    text = build(study_dir, record)
    out = study_dir / REPORT
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(out)
    print(f"wrote {out}")
    return 0
