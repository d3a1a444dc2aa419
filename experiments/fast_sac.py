"""The time to a return: ``preset=fast_sac`` beside ``algo=sac``'s defaults.

    python -m coherent_jax.study experiments/studies/fast_sac.yaml workers=1
    python experiments/fast_sac.py experiments/results/fast_sac [--out DIR]

Reads each run's ``metrics.jsonl`` of the study's cells (``TASK/sac/CONFIG/sweep``, `CONFIGS`),
keeps its evaluations (env steps, wall seconds since the run started, compile included,
and the deterministic evaluation's mean return), writes them to ``DIR/evaluations.csv``
(default: the study's folder) and prints a Markdown table per task.

The target of a task is fixed by a rule, not chosen after looking: the highest return
that *every* run of the task (every configuration, every seed) reached at some
evaluation, i.e. the minimum over runs of each run's best evaluation. For each run the
table gives the first evaluation at or above it: its wall seconds and env steps; then the
medians over seeds and the ratio of the defaults' median seconds to each other's. Beside
it, each run's best return within the same wall time for all: the shortest run's.
``--target R`` gives each run's time to a return R of your own instead; a run that never
reaches it counts as infinitely slow in the median.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
from pathlib import Path

CONFIGS = ("default", "fast", "batch64")
RETURN = "eval/episode_return"


def evaluations(run: Path) -> list[tuple[int, float, float]]:
    """(env steps, wall seconds, return) of each evaluation of a run, in order."""
    rows = []
    for line in (run / "metrics.jsonl").read_text().splitlines():
        row = json.loads(line)
        if row.get(RETURN) is not None:
            rows.append((int(row["env_steps"]), float(row["time_s"]), float(row[RETURN])))
    return rows


def read_study(folder: Path) -> dict[tuple[str, str, int], list[tuple[int, float, float]]]:
    """{(task, config, seed): evaluations} of every run found under the study's folder."""
    runs = {}
    for metrics in sorted(folder.glob("*/sac/*/sweep/p*-seed=*/metrics.jsonl")):
        run = metrics.parent
        config = run.parents[1].name
        if config in CONFIGS:
            seed = int(run.name.split("seed=")[1])
            runs[(run.parents[3].name, config, seed)] = evaluations(run)
    return runs


def first_reaching(evals: list[tuple[int, float, float]], target: float) -> tuple[int, float] | None:
    return next(((steps, wall) for steps, wall, ret in evals if ret >= target), None)


def table(task: str, runs: dict, target: float | None = None) -> list[str]:
    mine = {k: v for k, v in runs.items() if k[0] == task and v}
    how = "given"
    if target is None:
        target = min(max(r for _, _, r in evals) for evals in mine.values())
        how = "the lowest of the runs' best evaluations"
    # The same wall time for every run: the shortest run's.
    wall_all = min(evals[-1][1] for evals in mine.values())
    lines = [
        f"{task}: target return {target:.1f} ({how}); equal wall time {wall_all:.0f} s (the shortest run's)",
        "",
        "| config | seed | wall s to target | env steps to target | best return "
        f"| best return by {wall_all:.0f} s | env steps/s per seed |",
        "|---|---|---|---|---|---|---|",
    ]
    medians = {}
    for config in CONFIGS:
        walls = []
        for (_, c, seed), evals in sorted(mine.items()):
            if c != config:
                continue
            reached = first_reaching(evals, target)
            steps, wall = reached if reached else (None, float("inf"))
            walls.append(wall)
            rate = evals[-1][0] / evals[-1][1]
            best = max(r for _, _, r in evals)
            by_wall = max((r for _, w, r in evals if w <= wall_all), default=float("nan"))
            to = f"{wall:.0f} | {steps:,}" if reached else "not reached | -"
            lines.append(f"| {config} | {seed} | {to} | {best:.1f} | {by_wall:.1f} | {rate:.0f} |")
        if walls:
            medians[config] = statistics.median(walls)
    lines += ["", "median wall s to target: " + ", ".join(f"{c} {m:.0f}" for c, m in medians.items())]
    lines += [f"default / {c}: {medians['default'] / m:.2f}x" for c, m in medians.items() if c != "default"]
    return [*lines, ""]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", type=Path)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--target", type=float, default=None, help="a return of your own (default: the rule)")
    args = parser.parse_args(argv)
    runs = read_study(args.study)
    if not runs:
        print(f"error: no runs of {CONFIGS} under {args.study}", file=sys.stderr)
        return 2
    out = (args.out or args.study) / "evaluations.csv"
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".csv.tmp")
    with tmp.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["task", "config", "seed", "env_steps", "time_s", "eval_return"])
        for (task, config, seed), evals in sorted(runs.items()):
            writer.writerows([task, config, seed, s, f"{w:.2f}", f"{r:.3f}"] for s, w, r in evals)
    tmp.replace(out)
    for task in sorted({k[0] for k in runs}):
        print("\n".join(table(task, runs, args.target)))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
