"""RESULTS.md from the finished cells: ``python experiments/report.py [--results DIR] [--out FILE]``.

Reads every finished cell under ``experiments/results/`` (see ``reproduce.py``) and
writes ``experiments/RESULTS.md`` with its figures in ``experiments/results/figures/``:

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
  the code at HEAD no longer reproduces bit for bit (``RESULTS/verify.json``, `verify`);
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
import importlib.util
import json
import os
import sys
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coherent_jax import plot  # noqa: E402

_spec = importlib.util.spec_from_file_location("reproduce", ROOT / "experiments" / "reproduce.py")
reproduce = importlib.util.module_from_spec(_spec)
sys.modules.setdefault("reproduce", reproduce)
_spec.loader.exec_module(reproduce)
import classic  # noqa: E402  (the classic suite's goal table)
import curves  # noqa: E402  (beside reproduce.py, which put experiments/ on sys.path)
import stats  # noqa: E402
import verify  # noqa: E402
from stats import REPS, aggregate, auc, interval, normalised, probability_of_improvement  # noqa: E402,F401

METRIC = "eval/episode_return"
BASELINES = ("action", "noisynet", "psne")


# On the sparse tasks the reward is 0 outside the target set, so a training episode with
# a positive return is one in which the exploration got there at least once: a run first
# reached the reward where its `REACH_METRIC` (the mean over the episodes an iteration
# completed) is first above 0.
REACH_METRIC = "train/episode_return"
reached_reward = stats.first_positive


def reach_rows(cell: reproduce.Cell, results: Path) -> list[str]:
    """Table rows: per strategy of a sparse cell, the seeds that ever reached the reward."""
    runs = curves.load_runs(results, cell.suite, cell.name, REACH_METRIC)
    rows = []
    for label in sorted({_label(cell, r) for r in runs}):
        hit, n, first = stats.reach_summary([r for r in runs if _label(cell, r) == label])
        rows.append(f"| {cell.setting('env')} | {label} | {hit} of {n} | {first} |")
    return rows


def cell_runs(cell: reproduce.Cell, results: Path) -> list[plot.Run]:
    """The seeds' runs of a finished cell (one per sweep point): from the points' logs where
    they are present, else from the suite's curves table (`curves.py`)."""
    return curves.load_runs(results, cell.suite, cell.name, METRIC)


# Suites whose comparisons are claims of the thesis; the others' (sparse: tasks the
# thesis did not run) are our own questions, which hold or do not.
THESIS_SUITES = ("thesis", "ablations", "protocol")


def verdict(poi: dict[str, float], suite: str = "thesis") -> str:
    yes, no = ("reproduced", "not reproduced") if suite in THESIS_SUITES else ("holds", "does not hold")
    if poi["low"] > 0.5:
        return yes
    if poi["high"] < 0.5:
        return no
    return "inconclusive"


def aggregate_table(
    algo: str, what: str, table: dict[str, dict[str, np.ndarray]], norm, title: str = ""
) -> list[str]:
    """RESULTS.md lines: IQM and optimality gap of every strategy on the tasks all have finished;
    `title` names the group of cells compared (a suite with several, `label_groups`)."""
    agg = aggregate(norm)
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


def _label(cell: reproduce.Cell, run: plot.Run, suite: str | None = None) -> str:
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
        cells = reproduce.SUITES[suite]()
        done = [c for c in cells if reproduce.cell_state(c, results) == "done"]
        missing += [f"{suite}: {c.name} ({reproduce.cell_state(c, results)})" for c in cells if c not in done]
        still_needed += sum(reproduce.estimated_seconds(c, results) for c in cells if c not in done)
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
    done: list[reproduce.Cell],
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
    lines += verify.provenance_lines([c for c in done if c.suite == suite], results)
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
                    lines += aggregate_table(algo, what, group, norm, title)
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
    suite: str, done: list[reproduce.Cell], runs: dict[str, list[plot.Run]]
) -> list[tuple[str, list[reproduce.Cell]]]:
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
    suite: str, done: list[reproduce.Cell], runs: dict[str, list[plot.Run]], figures: Path, out: Path
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


def cell_table(suite: str, done: list[reproduce.Cell], runs: dict[str, list[plot.Run]], results: Path):
    """The table of cells (seeds, final return and area with 95% CIs, rate, wall time).

    Returns its lines, the final returns and areas per algorithm, label and task (one
    value per seed), and the wall times of the suite's own cells (a reference cell
    counts in its own suite).
    """
    lines = [
        "| cell | seeds | final return (95% CI) | area under curve (95% CI) | env steps/s | wall |",
        "|---|---|---|---|---|---|",
    ]
    finals: dict[str, dict[str, dict[str, np.ndarray]]] = defaultdict(lambda: defaultdict(dict))
    aucs: dict[str, dict[str, dict[str, np.ndarray]]] = defaultdict(lambda: defaultdict(dict))
    walls: list[float] = []
    entries = verify.load(results)  # a cell HEAD no longer reproduces bit for bit is marked
    for c in done:
        rs = runs[c.name]
        f = np.array([r.values[-1] for r in rs])
        a = np.array([auc(r) for r in rs])
        for label in sorted({_label(c, r, suite) for r in rs}):
            keep = [i for i, r in enumerate(rs) if _label(c, r, suite) == label]
            finals[c.setting("algo")][label][c.setting("env")] = f[keep]
            aucs[c.setting("algo")][label][c.setting("env")] = a[keep]
        summary = json.loads((reproduce.cell_dir(c, results) / "sweep" / "sweep.json").read_text())
        wall = float(summary.get("wall_s", 0.0))
        walls.append(wall if c.suite == suite else 0.0)
        name = (c.name if c.suite == suite else f"{c.name} ({c.suite} suite)") + verify.mark(c, entries)
        fm, fl, fh = interval(f)
        am, al, ah = interval(a)
        lines.append(
            f"| {name} | {len(rs)} | {fm:.0f} ({fl:.0f}, {fh:.0f}) | {am:.0f} ({al:.0f}, {ah:.0f}) | "
            f"{summary.get('sweep_env_steps_per_s', float('nan')):.0f} | {wall / 3600:.2f} h |"
        )
    lines += [*verify.footnote(done, entries), ""]
    return lines, finals, aucs, walls


def sparse_lines(done: list[reproduce.Cell], results: Path) -> list[str]:
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
    claims = []
    for coherent, baseline in _pairs(suite, per_label):
        pair = normalised({coherent: per_label[coherent], baseline: per_label[baseline]})
        if not pair:
            continue
        poi = probability_of_improvement(pair[coherent], pair[baseline])
        tasks = pair[coherent].shape[1]
        claims.append(
            (
                f"{suite}, {algo}, {what}: {coherent} improves on {baseline} ({tasks} task(s))",
                verdict(poi, suite),
                poi,
            )
        )
    return claims


def verdict_lines(claims: list[tuple[str, str, dict[str, float]]]) -> list[str]:
    """The verdicts table (empty without claims)."""
    if not claims:
        return []
    lines = ["## Verdicts", "", "| claim | P(improvement) (95% CI) | verdict |", "|---|---|---|"]
    lines += [f"| {c} | {p['p']:.2f} ({p['low']:.2f}, {p['high']:.2f}) | {v} |" for c, v, p in claims]
    lines.append("")
    return lines


def compute_lines(total_wall: float, missing: list[str], still_needed: float) -> list[str]:
    """The compute section: wall time spent, the budget per cell, and the cells not finished."""
    lines = [
        "## Compute",
        "",
        f"Wall time of the finished cells: {total_wall / 3600:.1f} h on the 2-core CPU, two cells"
        " running side by side most of the time.",
        "",
        f"Budget per cell: {reproduce.SEEDS} seeds of {reproduce.ONPOLICY_STEPS:,} env steps for"
        f" A2C and PPO; SAC {reproduce.SAC_STEPS:,} env steps at {', '.join(reproduce.SAC_SETTINGS)}"
        " (see `reproduce.py`: 1M steps at UTD 1 would take about 9 hours per SAC cell here).",
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


def _reference_cells(suite: str, done: list[reproduce.Cell], results: Path) -> list[reproduce.Cell]:
    """The thesis suite's finished cells a suite is read beside. The ablations: the action
    and coherent cells of their task and algorithms, the defaults each ablation varies one
    component of (coherent: beta 0.01, analytic integration, the exact gradient). `beyond`:
    every thesis strategy on each task and algorithm a newer strategy has run, at the same
    settings, so that the newer strategies are compared with all four."""
    if suite == "ablations":
        algos = {c.setting("algo") for c in done}

        def keep(c: reproduce.Cell) -> bool:
            return (
                c.setting("env") == reproduce.ABLATION_TASK
                and c.setting("algo") in algos
                and c.setting("explore") in ("action", "coherent")
            )
    elif suite == "beyond":
        runs = {(c.setting("env"), c.setting("algo")) for c in done}

        def keep(c: reproduce.Cell) -> bool:
            return (c.setting("env"), c.setting("algo")) in runs
    elif suite == "protocol":
        return _chain_references(done, results)
    else:
        return []
    return [c for c in reproduce.thesis_cells() if keep(c) and reproduce.cell_state(c, results) == "done"]


def _chain_references(done: list[reproduce.Cell], results: Path) -> list[reproduce.Cell]:
    """The protocol suite's chain-length cells (`coherent.gradient=episode`, ``stored``, at the
    library's defaults) are read beside the ``exact`` cells of their task, the thesis suite's
    PPO coherent cells, and HalfCheetah's stored one of the ablations suite."""
    tasks = {c.setting("env") for c in done if c.name.endswith(("/coherent-episode", "/coherent-stored"))}
    stored = f"{reproduce.ABLATION_TASK}/ppo/coherent-stored"
    candidates = [
        *(c for c in reproduce.thesis_cells() if c.name in {f"{t}/ppo/coherent" for t in tasks}),
        *(c for c in reproduce.ablation_cells() if c.name == stored),
    ]
    keep = [c for c in candidates if c.setting("env") in tasks]
    return [c for c in keep if reproduce.cell_state(c, results) == "done"]


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
    newer = reproduce.BEYOND_LABELS
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
