"""A study's tuning stage: each strategy tuned with the same budget (`coherent_jax.study.tune`
reads the ``tune:`` block), its values chosen, then its evaluation cells run at them.

``python -m coherent_jax.study STUDY.yaml`` runs the tuning first (`run_stage`): with method
grid, one cell per unit (``TASK/ALGO/LABEL@tune``) whose sweep vmaps the space's grid x the
tuning seeds, run by the study's executor like any cell; with method optuna,
`coherent_jax.study.optuna_search`. A candidate's score is the metric (``auc`` or
``final``) of each tuning seed's evaluation curve, mean over the seeds (-inf when a seed
diverged). The choice (`choose`) is per strategy and algorithm: the candidate of the highest
score on one task; on several, the highest mean over the tasks of its score min-max
normalised per task over the strategy's candidates; with ``per_task: true``, per task. The
tuning's record, ``tune.json`` in the study's folder (what was searched, each candidate's
score, the env steps spent, the values chosen and each evaluation cell's items), is written
once every unit is done; `resolve` reads it back into the study, whose evaluation cells then
take the chosen values. An evaluation cell that ran at other values is refused as a cell of
another specification (`coherent_jax.study.cell.check_cell_dir`), never mixed in.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coherent_jax.study import cost, execute, optuna_search, plan, tune
from coherent_jax.study.cell import Cell, cell_state

TUNE_FILE = "tune.json"


def units(study) -> list[Cell]:
    """The study's evaluation cells (before tuning) whose strategy it tunes."""
    return tune.units(study.tune, study.cells(tuned=False))


def cells(study) -> list[Cell]:
    """The study's tuning cells known before it runs (method grid's; an Optuna trial is made as
    the search runs)."""
    return [] if study.tune is None else tune.tuning_cells(study.tune, study.cells(tuned=False))


def read(study_dir: Path) -> dict[str, Any] | None:
    """The study's ``tune.json``, or None."""
    try:
        return json.loads((Path(study_dir) / TUNE_FILE).read_text())
    except (OSError, ValueError):
        return None


def resolve(study):
    """The study with the values its finished tuning chose (as it is without ``tune:`` or
    before its tuning is done)."""
    if study.tune is None:
        return study
    record = read(study.out)
    if record is None or record.get("fingerprint") != tune.fingerprint(study.tune, study.cells(tuned=False)):
        return study
    return dataclasses.replace(study, chosen={k: tuple(v) for k, v in record["chosen"].items()})


def check_folder(study) -> None:
    """Refuses tuning results of another specification in the study's folder."""
    if study.tune is not None:
        execute.check_folder(study.out, study.name, [*cells(study), *study.cells()])
        optuna_search.check_searches(study.tune, units(study), study.out)


# ------------------------------------------------------------------ scores and the choice
def grid_result(spec: tune.Tune, unit: Cell, out: Path) -> dict[str, Any]:
    """A grid unit's candidates (values, score) in grid order, and the env steps it spent."""
    cell = tune.grid_cell(spec, unit)
    grid = json.loads((out / cell.name / "sweep" / "grid.json").read_text())
    points = [dict(zip(grid["axes"], combo, strict=True)) for combo in _product(grid["axes"].values())]
    by_point: dict[int, list] = defaultdict(list)
    for i, curve in enumerate(tune.seed_curves(out, cell)):
        by_point[i // len(grid["seeds"])].append(curve)
    found = []
    for i, values in enumerate(points):
        score = tune.mean_score(by_point.get(i, []), spec.metric)
        found.append(
            {"values": values, "score": score if math.isfinite(score) else None, "state": "complete"}
        )
    return {"unit": unit.name, "candidates": found, "env_steps": tune.spent_steps(cell, out)}


def _product(lists) -> list[tuple]:
    combos: list[tuple] = [()]
    for values in lists:
        combos = [(*c, v) for c in combos for v in values]
    return combos


def _best(scores: Sequence[float]) -> int:
    """The index of the highest score (the first of equals; the first candidate if none is finite)."""
    top = max(scores, default=-math.inf)
    return scores.index(top) if math.isfinite(top) else 0


def _counted(candidate: dict[str, Any]) -> float:
    """A candidate's score in the choice: a complete one's (a pruned trial's is -inf)."""
    complete = candidate["state"] == "complete" and candidate["score"] is not None
    return candidate["score"] if complete else -math.inf


def _normalised(scores: list[float]) -> list[float]:
    """Scores min-max normalised over the finite ones (-inf stays; all equal: 0.5)."""
    finite = [s for s in scores if math.isfinite(s)]
    lo, hi = (min(finite), max(finite)) if finite else (0.0, 0.0)
    return [-math.inf if not math.isfinite(s) else (s - lo) / (hi - lo) if hi > lo else 0.5 for s in scores]


def _group_choice(group: list[dict[str, Any]]) -> tuple[dict[str, Any], float | None]:
    """One choice for a group's units: on one task the highest score; on several (a grid's same
    candidates on each) the highest mean score normalised per task."""
    scores = [[_counted(c) for c in r["candidates"]] for r in group]
    if len(group) == 1:
        i = _best(scores[0])
        return group[0]["candidates"][i]["values"], group[0]["candidates"][i]["score"]
    norm = [_normalised(s) for s in scores]
    means = [sum(col) / len(col) for col in zip(*norm, strict=True)]
    i = _best(means)
    return group[0]["candidates"][i]["values"], means[i] if math.isfinite(means[i]) else None


def choose(spec: tune.Tune, unit_cells: Sequence[Cell], found: Sequence[dict[str, Any]]):
    """The choices (per strategy and algorithm, or per task too) and each unit's items."""
    by_name = {u.name: u for u in unit_cells}
    groups: dict[tuple, list[dict[str, Any]]] = defaultdict(list)
    for r in found:
        task, algo, label = r["unit"].split("/", 2)
        groups[(label, algo, task if spec.per_task else "")].append(r)
    choices, chosen = [], {}
    for (label, algo, _), group in groups.items():
        values, score = _group_choice(group)
        tasks = [r["unit"].split("/", 1)[0] for r in group]
        choices.append({"label": label, "algo": algo, "tasks": tasks, "values": values, "score": score})
        for r in group:
            unit = by_name[r["unit"]]
            keys = tune.keys_of(spec, label, unit)
            chosen[r["unit"]] = [f"{k}={tune.text(values[k])}" for k in keys]
    return choices, chosen


def write(study, found: Sequence[dict[str, Any]]) -> None:
    """``tune.json``: the block, each unit's candidates and spending, the choices, the items."""
    spec, unit_cells = study.tune, units(study)
    choices, chosen = choose(spec, unit_cells, found)
    steps = {u.name: tune.steps(spec, u) for u in unit_cells}
    record = {
        "fingerprint": tune.fingerprint(spec, study.cells(tuned=False)),
        **spec.spec(),
        "evaluation_seeds": sorted({s for c in study.cells(tuned=False) for s in tune.evaluation_seeds(c)}),
        "untuned": [label for label in study.labels() if label not in spec.space],
        "units": [{**r, "steps": steps[r["unit"]]} for r in found],
        "choices": choices,
        "chosen": chosen,
    }  # fmt: skip
    tmp = study.out / (TUNE_FILE + ".tmp")
    tmp.write_text(json.dumps(record, indent=1) + "\n")
    os.replace(tmp, study.out / TUNE_FILE)


# ------------------------------------------------------------------ the stage
def run_stage(study, executor) -> tuple[Any, list[str]]:
    """Runs the tuning not done (the study's lock held); the study at the chosen values, and the
    tuning cells (or searches) that failed."""
    done = resolve(study)
    if done.chosen is not None:
        print(f"[study] {study.name}: tuning done ({TUNE_FILE})", flush=True)
        return done, []
    spec = study.tune
    print(f"[study] {study.name}: tuning {len(units(study))} cells by {spec.method}, budget {spec.budget}")
    if spec.method == "grid":
        tuning = cells(study)
        failed = execute.run_cells(
            tuning, study.out, study.base, executor, probed=plan.cached_rates(tuning, study.base)
        )
        for cell in [c for c in tuning if c.name in failed and cell_state(c, study.out) == "done"]:
            execute.finish_cell(cell, study.out)  # a sweep whose point diverged: its candidate scores -inf
            failed.remove(cell.name)
        if failed:
            return study, failed
        found = [grid_result(spec, u, study.out) for u in units(study)]
    else:
        failed = optuna_search.run(study, executor)
        if failed:
            return study, failed
        found = optuna_search.results(study)
    write(study, found)
    resolved = resolve(study)
    for c in read(study.out)["choices"]:
        print(f"[study] tuned {c['label']} ({c['algo']}, {', '.join(c['tasks'])}): {c['values']}", flush=True)
    return resolved, []


def status_text(study) -> str:
    """The tuning's state: its cells' (grid) or trials' (optuna), and the values chosen."""
    head = f"tuning ({study.tune.method}, budget {study.tune.budget} per strategy):"
    if study.tune.method == "grid":
        body = cost.status(cells(study), study.out)
    else:
        body = "\n".join(optuna_search.status_lines(study))
    record = read(study.out) if resolve(study).chosen is not None else None
    tail = (
        "the evaluation cells wait for the tuning"
        if record is None
        else "chosen: " + "; ".join(f"{c['label']} ({c['algo']}): {c['values']}" for c in record["choices"])
    )
    return "\n".join([head, body, tail, ""])


def plan_cells(study) -> list[Cell]:
    """What the tuning will run, for a plan: method grid's cells; for optuna, `budget` trials per
    unit at its space's first values (a pruned trial costs less)."""
    if study.tune is None or resolve(study).chosen is not None:
        return []
    if study.tune.method == "grid":
        return cells(study)
    first = {}
    for u in units(study):
        dims = tune.keys_of(study.tune, u.label, u)
        first[u.name] = {k: d.low if isinstance(d, tune.Range) else d[0] for k, d in dims.items()}
    return [
        tune.trial_cell(study.tune, u, n, first[u.name])
        for u in units(study)
        for n in range(study.tune.budget)
    ]


def selected(study, chosen_cells: Sequence[Cell]) -> list[Cell]:
    """`chosen_cells` (selected before the tuning) at the values it chose."""
    names = {c.name for c in chosen_cells}
    return [c for c in study.cells() if c.name in names]


def record(study) -> dict[str, Any] | None:
    """What ``study.json`` says of the tuning (the report reads ``tune.json`` beside it)."""
    return None if study.tune is None else study.tune.spec()


# ------------------------------------------------------------------ the report's section
def _seeds(seeds: Sequence[int]) -> str:
    if not seeds:
        return "none"
    whole = list(seeds) == list(range(seeds[0], seeds[-1] + 1))
    return f"{seeds[0]}..{seeds[-1]}" if whole and len(seeds) > 1 else ", ".join(map(str, seeds))


def _values(values: dict[str, Any]) -> str:
    return ", ".join(f"`{k}={tune.text(v)}`" for k, v in values.items()) or "-"


def _score(x: float | None) -> str:
    return "-inf" if x is None else f"{x:.4g}"


def protocol(record: dict[str, Any]) -> str:
    """The tuning's protocol in words."""
    how = (
        "a grid: one vmapped sweep per strategy, task and algorithm of its candidates x the tuning seeds"
        if record["method"] == "grid"
        else f"Optuna's TPE (seeded, its first {optuna_search.startup(record['budget'])} trials at random), "
        "one sweep of the tuning seeds per trial, trials below the median of the earlier ones on the "
        "learning curve pruned"
    )
    across = (
        "per task"
        if record["per_task"]
        else "across the tasks: the highest mean of the scores min-max normalised per task over the "
        "strategy's candidates"
    )
    return (
        f"Each strategy was tuned before its evaluation with the same budget, {record['budget']} candidates "
        f"of {len(record['seeds'])} seeds each, by {how}. A candidate's score is its `{record['metric']}` "
        f"(mean over the tuning seeds; -inf when a seed diverged); the values chosen are the best {across}. "
        f"Tuning seeds {_seeds(record['seeds'])}; evaluation seeds {_seeds(record['evaluation_seeds'])}: "
        + ("disjoint." if not set(record["seeds"]) & set(record["evaluation_seeds"]) else "**not disjoint**.")
    )


def report_lines(study_dir: Path) -> list[str]:
    """The report's section "Tuning" from ``tune.json`` (a note when the tuning is not done)."""
    record = read(study_dir)
    lines = ["## Tuning", ""]
    if record is None:
        return [*lines, "The tuning is not done: the evaluation cells wait for it.", ""]
    lines += [protocol(record), ""]
    lines += [
        "| tuning cell | candidates | seeds x env steps | env steps spent | chosen | its score |",
        "|---|---|---|---|---|---|",
    ]
    chosen = {(c["label"], c["algo"], t): c for c in record["choices"] for t in c["tasks"]}
    unequal = []
    for u in record["units"]:
        task, algo, label = u["unit"].split("/", 2)
        c = chosen[(label, algo, task)]
        own = next((x["score"] for x in u["candidates"] if x["values"] == c["values"]), None)
        ran = sum(x["state"] in ("complete", "pruned") for x in u["candidates"])
        if ran < record["budget"]:
            unequal.append(f"{u['unit']} ran {ran} candidates")
        states = [x["state"] for x in u["candidates"]]
        pruned = f" ({states.count('pruned')} pruned)" if "pruned" in states else ""
        lines.append(
            f"| {u['unit']}{tune.SUFFIX} | {ran}{pruned} | {len(record['seeds'])} x {u['steps']:,} | "
            f"{u['env_steps']:,} | {_values(c['values'])} | {_score(own)} |"
        )
    lines.append("")
    if unequal or record["untuned"]:
        parts = [*unequal, *(f"{label} was not tuned" for label in record["untuned"])]
        lines += [f"**Unequal budgets** (budget {record['budget']} candidates): {'; '.join(parts)}.", ""]
    lines += [
        "Every candidate's score:",
        "",
        "| tuning cell | candidate | score | state |",
        "|---|---|---|---|",
    ]
    for u in record["units"]:
        for x in u["candidates"]:
            lines.append(
                f"| {u['unit']}{tune.SUFFIX} | {_values(x['values'])} | {_score(x['score'])} | {x['state']} |"
            )
    return [*lines, ""]
