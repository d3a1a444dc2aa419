"""RESULTS.md from the finished cells: ``python experiments/report.py [--results DIR] [--out FILE]``.

Reads every finished cell of the suites (``experiments/studies/*.yaml``, run by
``reproduce.py``) under ``experiments/results/`` and writes ``experiments/RESULTS.md`` with
its figures in ``experiments/results/figures/``; the tables and statistics are the package's
(`coherent_jax.study.tables`, `coherent_jax.study.stats`), the suites' reading of each
other here:

* learning curves per suite, task and algorithm: the mean of the deterministic
  evaluation return over seeds and its 95% percentile-bootstrap interval, against
  env steps (`coherent_jax.plot`);
* final returns: per cell, the mean final evaluation return over seeds with its
  bootstrap interval, and the area under the curve (mean evaluation return over
  training, a measure of learning speed);
* aggregates with rliable (Agarwal et al. 2021): per algorithm, scores normalised per
  task (min-max over all cells of that task), IQM and optimality gap with 95%
  stratified-bootstrap intervals, and the probability that coherent exploration
  improves on each baseline, for final score and for area under the curve;
* env steps/s and wall time per cell, and the compute spent in all; a † on the cells that
  the code at HEAD no longer reproduces bit for bit (``RESULTS/verify.json``,
  `coherent_jax.study.verify`);
* for each claim of the thesis, a verdict: *reproduced* when the 95% interval of the
  probability of improvement lies above 0.5, *not reproduced* when it lies below,
  *inconclusive* otherwise (on the sparse tasks and MountainCar, which the thesis did not
  run, and for coherent against gSDE, pink and Lattice, which it did not compare, the
  comparison *holds* or *does not hold*);
* on the sparse tasks, the seeds that ever reached the reward; on MountainCar (the
  `classic` suite, `classic.py`), the seeds that ever reached the goal in training and
  those whose final policy reaches it, beside the returns.

The ablations are read beside the thesis suite's action and coherent cells of their task,
and `beyond` (gSDE, pink at exponents 1 and 0.5, Lattice) beside every thesis strategy on the
same tasks and algorithms. The `protocol` suite (``preset=thesis``) is three comparisons,
each aggregated among its own cells: the thesis's strategies, the beta ablation, and the
chain length at the library's defaults (``episode`` and ``stored`` beside the thesis
suite's ``exact`` cells).

Missing cells are listed, never silently left out.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "experiments"), str(ROOT)]

import classic  # noqa: E402  (the classic suite's goal table)
import reproduce  # noqa: E402  (the suites: experiments/studies/*.yaml)

from coherent_jax import plot  # noqa: E402
from coherent_jax.study import stats, tables, verify  # noqa: E402
from coherent_jax.study.cell import Cell, cell_state  # noqa: E402
from coherent_jax.study.cost import estimated_seconds  # noqa: E402
from coherent_jax.study.stats import REPS, normalised  # noqa: E402

METRIC = "eval/episode_return"
BASELINES = ("action", "noisynet", "psne")
ABLATION_TASK = "halfcheetah"  # the ablations suite's task (experiments/studies/ablations.yaml)


# On the sparse tasks the reward is 0 outside the target set, so a training episode with
# a positive return is one in which the exploration got there at least once: a run first
# reached the reward where its `REACH_METRIC` (the mean over the episodes an iteration
# completed) is first above 0.
REACH_METRIC = "train/episode_return"
reached_reward = stats.first_positive


def reach_rows(cell: Cell, results: Path) -> list[str]:
    """Table rows: per strategy of a sparse cell, the seeds that ever reached the reward."""
    runs = stats.load_runs(results / cell.suite, cell.name, REACH_METRIC)
    return tables.reach_rows(cell, runs, _label, task=True)


def cell_runs(cell: Cell, results: Path) -> list[plot.Run]:
    """The seeds' runs of a finished cell (one per sweep point): from the points' logs where
    they are present, else from the suite's curves table (`coherent_jax.study.curves`)."""
    return stats.load_runs(results / cell.suite, cell.name, METRIC)


# Suites whose comparisons are claims of the thesis; the others' (sparse: tasks the
# thesis did not run) are our own questions, which hold or do not.
THESIS_SUITES = ("thesis", "ablations", "protocol")


def verdict_words(suite: str) -> tuple[str, str]:
    """A thesis suite's claims are *reproduced* or not; the others' (our own questions) hold or not."""
    return ("reproduced", "not reproduced") if suite in THESIS_SUITES else ("holds", "does not hold")


def verdict(poi: dict[str, float], suite: str = "thesis") -> str:
    return tables.verdict(poi, *verdict_words(suite))


def _label(cell: Cell, run: plot.Run, suite: str | None = None) -> str:
    """The strategy (``coherent``, ``psne``, ``coherent-mc``...); the cells and grid points
    that vary beta by their beta, and so, in the ablations, the thesis's coherent cell
    (the default beta, which every other ablation keeps). In the protocol suite a cell's
    ``-thesis`` (the preset) is dropped, and the thesis suite's coherent cell it is read
    beside is ``coherent-exact`` (the chain cut at every 64-step segment)."""
    name = cell.name.split("/", 2)[2]
    if suite == "protocol":
        if cell.suite == "thesis":
            return "coherent-exact"
        name = name.replace("-thesis", "", 1)
    if name.startswith("coherent-beta") or (suite == "ablations" and name == "coherent"):
        return f"beta={float(run.settings['coherent.beta']):g}"
    return name


SUITES = ("thesis", "ablations", "beyond", "sparse", "protocol", "classic")  # in RESULTS.md's order


def build(results: Path, out: Path, suites: Sequence[str] = SUITES) -> str:
    """RESULTS.md's text: per suite its curves, cell table, provenance and aggregates, then the
    verdicts on the claims, the compute spent and the cells not finished."""
    lines = [
        "# Results",
        "",
        f"Generated by `python experiments/report.py` from `{os.path.relpath(results, ROOT)}/`.",
        "",
    ]
    total_wall, missing, still_needed = 0.0, [], 0.0
    claims: list[tuple[str, str, dict[str, float]]] = []
    for suite in suites:
        cells = reproduce.select(suite, [], results)
        done = [c for c in cells if cell_state(c, results / suite) == "done"]
        missing += [f"{suite}: {c.name} ({cell_state(c, results / suite)})" for c in cells if c not in done]
        still_needed += sum(estimated_seconds(c, results / suite) for c in cells if c not in done)
        if not done:
            continue
        done += _reference_cells(suite, done, results)
        section, walls = suite_section(suite, done, results, out, claims)
        lines += section
        for wall in walls:
            total_wall += wall
    lines += verdict_lines(claims)
    lines += compute_lines(total_wall, missing, still_needed)
    return "\n".join(lines)


def suite_section(
    suite: str,
    done: list[Cell],
    results: Path,
    out: Path,
    claims: list[tuple[str, str, dict[str, float]]],
) -> tuple[list[str], list[float]]:
    """One suite's section (its claims appended to `claims`) and the wall times of its own cells."""
    lines = [f"## Suite `{suite}`", ""]
    runs = {c.name: cell_runs(c, results) for c in done}
    for title, members in cell_groups(suite, done, runs):
        name = suite + (f"-{title.split()[0]}" if title else "")
        lines += curve_figures(name, members, runs, results / "figures", out)
    table, finals, aucs, walls = cell_table(suite, done, runs, results)
    lines += table
    lines += verify.provenance_lines([c for c in done if c.suite == suite], study_dirs(results))
    if suite == "sparse":
        lines += sparse_lines(done, results)
    if suite == "classic":
        lines += classic.classic_lines(done, results, _label)
    for algo in sorted(finals):
        for what, per_label in (("final return", finals[algo]), ("area under curve", aucs[algo])):
            for title, labels in label_groups(suite, per_label):
                group = {k: per_label[k] for k in labels}
                norm = normalised(group)
                if len(norm) >= 2:
                    lines += tables.aggregate_table(algo, what, group, norm, title)
            claims += suite_claims(suite, algo, what, per_label)
    return lines, walls


# The protocol suite's three questions, each compared within its own cells: the thesis's
# strategies under its protocol, the beta ablation (HalfCheetah, its coherent cell at the
# default beta among them) and the chain length at the library's defaults.
CHAIN_LABELS = ("coherent-exact", "coherent-episode", "coherent-stored")


def label_groups(suite: str, labels) -> list[tuple[str, list[str]]]:
    """(title, labels) of each group of a suite's labels compared among themselves; one
    untitled group of every label but in the protocol suite."""
    labels = sorted(labels)
    if suite != "protocol":
        return [("", labels)]
    betas = [k for k in labels if k.startswith("beta=")]
    groups = [
        ("", [k for k in labels if k in (*BASELINES, "coherent")]),
        ("beta ablation", betas + (["coherent"] if betas and "coherent" in labels else [])),
        ("chain length", [k for k in labels if k in CHAIN_LABELS]),
    ]
    return [(t, g) for t, g in groups if g]


def cell_groups(
    suite: str, done: list[Cell], runs: dict[str, list[plot.Run]]
) -> list[tuple[str, list[Cell]]]:
    """(title, cells) per `label_groups` group, for its figures: a group's cells are those
    with its labels on the tasks its own labels (not one it shares) have run."""
    label = {c.name: _label(c, runs[c.name][0], suite) for c in done if runs[c.name]}
    groups = label_groups(suite, set(label.values()))
    out = []
    for i, (title, labels) in enumerate(groups):
        shared = {k for j, (_, g) in enumerate(groups) if j != i for k in g}
        own = {c.setting("env") for c in done if label.get(c.name) in set(labels) - shared}
        members = [c for c in done if label.get(c.name) in labels and (not own or c.setting("env") in own)]
        out.append((title, members))
    return out


def curve_figures(
    suite: str, done: list[Cell], runs: dict[str, list[plot.Run]], figures: Path, out: Path
) -> list[str]:
    """The learning curves: one figure per algorithm, one panel per task; their image lines."""
    lines: list[str] = []
    figures.mkdir(parents=True, exist_ok=True)
    by_algo: dict[str, list[plot.Run]] = defaultdict(list)
    for c in done:
        by_algo[c.setting("algo")] += runs[c.name]
    for algo, algo_runs in sorted(by_algo.items()):
        path = figures / f"{suite}-{algo}.png"
        plot.plot_curves(plot.group_curves(algo_runs), METRIC, path, REPS, 0)
        lines += [f"![{suite} {algo}]({os.path.relpath(path, out.parent)})", ""]
    return lines


def study_dirs(results: Path) -> dict[str, Path]:
    """Each suite's folder: ``results/SUITE``."""
    return {suite: results / suite for suite in reproduce.SUITES}


def cell_table(suite: str, done: list[Cell], runs: dict[str, list[plot.Run]], results: Path):
    """The table of cells (`coherent_jax.study.tables.cell_table`), each run labelled as the
    suite reads it (`_label`), a cell of another suite marked with its suite."""
    label = lambda c, r: _label(c, r, suite)  # noqa: E731
    entries = verify.load(results)  # a cell HEAD no longer reproduces bit for bit is marked
    return tables.cell_table(done, runs, study_dirs(results), label, entries, suite)


def sparse_lines(done: list[Cell], results: Path) -> list[str]:
    """The sparse suite's table: the seeds that reached the reward, and when they first did."""
    lines = [
        "Seeds whose exploration ever reached the sparse reward (a training episode",
        "with positive return), and the median env step of the first one. The",
        "tasks' episodes are 1,000 steps and all 64 envs end theirs together, so",
        "a seed reports returns every 64,000 env steps: that is the resolution of",
        "the first step.",
        "",
        "| task | strategy | seeds that reached it | first reached at (median env steps) |",
        "|---|---|---|---|",
    ]
    for c in done:
        lines += reach_rows(c, results)
    lines.append("")
    return lines


def suite_claims(
    suite: str, algo: str, what: str, per_label: dict[str, dict[str, np.ndarray]]
) -> list[tuple[str, str, dict[str, float]]]:
    """Each claim of the suite on the tasks both of its strategies have finished, with its verdict."""
    what = f"{suite}, {algo}, {what}"
    pairs = (tables.claim(a, b, per_label, what, verdict_words(suite)) for a, b in _pairs(suite, per_label))
    return [c for c in pairs if c is not None]


RULE = (
    "A claim is *reproduced* (on the tasks the thesis did not run and against the strategies it "
    "did not compare: *holds*) when the 95% stratified-bootstrap interval of the probability of "
    "improvement lies above 0.5, *not reproduced* (*does not hold*) when it lies below, and "
    "*inconclusive* otherwise."
)


def verdict_lines(claims: list[tables.Claim]) -> list[str]:
    """The verdicts table (empty without claims), after its rule."""
    return tables.verdict_lines(claims, RULE)


def compute_lines(total_wall: float, missing: list[str], still_needed: float) -> list[str]:
    """The compute section: wall time spent, the budget per cell, and the cells not finished."""
    thesis = reproduce.load("thesis")
    steps = thesis.grids[0].total_steps
    sac = " ".join(thesis.grids[0].algos["sac"])
    lines = [
        "## Compute",
        "",
        f"Wall time of the finished cells: {total_wall / 3600:.1f} h on the 2-core CPU, two cells"
        " running side by side most of the time.",
        "",
        f"Budget per cell: {thesis.seeds} seeds of {steps['default']:,} env steps for"
        f" A2C and PPO; SAC {steps['sac']:,} env steps at {sac}"
        " (see `experiments/studies/thesis.yaml`: 1M steps at UTD 1 would take about 9 hours per"
        " SAC cell here).",
        "",
    ]
    if missing:
        lines += [
            f"The {len(missing)} cells not finished need about {still_needed / 3600:.1f} h more"
            " (`python experiments/reproduce.py SUITE --status`).",
            "",
        ]
        lines += ["## Cells not finished", ""] + [f"- {m}" for m in missing] + [""]
    return lines


def _reference_cells(suite: str, done: list[Cell], results: Path) -> list[Cell]:
    """The thesis suite's finished cells a suite is read beside. The ablations: the action
    and coherent cells of their task and algorithms, the defaults each ablation varies one
    component of (coherent: beta 0.01, analytic integration, the exact gradient). `beyond`:
    every thesis strategy on each task and algorithm a newer strategy has run, at the same
    settings, so that the newer strategies are compared with all four."""
    if suite == "ablations":
        algos = {c.setting("algo") for c in done}

        def keep(c: Cell) -> bool:
            return (
                c.setting("env") == ABLATION_TASK
                and c.setting("algo") in algos
                and c.setting("explore") in ("action", "coherent")
            )
    elif suite == "beyond":
        runs = {(c.setting("env"), c.setting("algo")) for c in done}

        def keep(c: Cell) -> bool:
            return (c.setting("env"), c.setting("algo")) in runs
    elif suite == "protocol":
        return _chain_references(done, results)
    else:
        return []
    thesis = reproduce.select("thesis", [], results)
    return [c for c in thesis if keep(c) and cell_state(c, results / c.suite) == "done"]


def _chain_references(done: list[Cell], results: Path) -> list[Cell]:
    """The protocol suite's chain-length cells (`coherent.gradient=episode`, ``stored``, at the
    library's defaults) are read beside the ``exact`` cells of their task, the thesis suite's
    PPO coherent cells, and HalfCheetah's stored one of the ablations suite."""
    tasks = {c.setting("env") for c in done if c.name.endswith(("/coherent-episode", "/coherent-stored"))}
    stored = f"{ABLATION_TASK}/ppo/coherent-stored"
    candidates = [
        *(
            c
            for c in reproduce.select("thesis", [], results)
            if c.name in {f"{t}/ppo/coherent" for t in tasks}
        ),
        *(c for c in reproduce.select("ablations", [], results) if c.name == stored),
    ]
    keep = [c for c in candidates if c.setting("env") in tasks]
    return [c for c in keep if cell_state(c, results / c.suite) == "done"]


def _pairs(suite: str, norm: dict) -> list[tuple[str, str]]:
    """(coherent variant, what it is compared with) for the claims of each suite."""
    if suite == "ablations":
        pairs = [
            ("beta=0.01", "coherent-mc"),  # analytic vs single-sample Monte Carlo, default beta
            ("coherent-mc", "coherent-mc-all"),  # last layer vs all layers, both Monte Carlo
            ("beta=0.01", "coherent-stored"),  # the thesis's exact gradient vs the stored belief's
        ]
        # The chain: intermediate beta vs step-based (1) and trajectory-based (0) exploration.
        pairs += [(f"beta={b}", f"beta={e}") for b in ("0.01", "0.1", "0.5") for e in ("1", "0")]
        return [p for p in pairs if p[0] in norm and p[1] in norm]
    if suite == "protocol":
        pairs = [("coherent", b) for b in BASELINES]
        # beta 0.01 is the coherent cell; each intermediate beta against both ends of the chain
        pairs += [(b, e) for b in ("coherent", "beta=0.1", "beta=0.5") for e in ("beta=1", "beta=0")]
        pairs += [("coherent-episode", "coherent-exact"), ("coherent-episode", "coherent-stored")]
        return [p for p in pairs if p[0] in norm and p[1] in norm]
    # beyond: only the newer strategies; the thesis suite's own comparisons are its verdicts.
    newer = tuple(reproduce.load("beyond").labels())
    candidates = newer if suite == "beyond" else (*BASELINES, *newer)
    others = [b for b in candidates if b in norm]
    if suite in ("sparse", "classic"):  # coherent at each beta of its grid against every baseline
        return [(c, b) for c in sorted(norm) if c.startswith("beta=") for b in others]
    return [("coherent", b) for b in others if "coherent" in norm]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python experiments/report.py", description=__doc__.split("\n")[0])
    parser.add_argument("--results", default=str(reproduce.RESULTS))
    parser.add_argument("--out", default=str(ROOT / "experiments" / "RESULTS.md"))
    parser.add_argument(
        "--suites",
        nargs="+",
        default=list(SUITES),
        choices=list(reproduce.SUITES),
    )
    args = parser.parse_args(argv)
    results, out = Path(args.results).resolve(), Path(args.out).resolve()
    text = build(results, out, args.suites)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
