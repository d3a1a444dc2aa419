"""Reproduce the thesis's comparisons: ``python experiments/reproduce.py SUITE``.

A suite is a study file, ``experiments/studies/SUITE.yaml`` (its cells, their settings and
why), run by the package's ``python -m coherent_jax.study`` (`coherent_jax.study`); this
script is that command with the suites' results folder, ``experiments/results/SUITE/``:

    python experiments/reproduce.py thesis --status
    # the same: python -m coherent_jax.study experiments/studies/thesis.yaml status=true
    nohup python experiments/reproduce.py thesis > reproduce-thesis.log 2>&1 &
    python experiments/reproduce.py ablations --cells 'halfcheetah/ppo/*'
    python experiments/reproduce.py protocol --pack --commit
    python experiments/reproduce.py thesis --verify 'hopper/ppo/*'   # does HEAD still compute them?

Git keeps each finished cell's small files and its suite's curves table (``--commit``
commits exactly these; `coherent_jax.study.curves`), and a stopped cell's ``carry.tar.gz``
(``--pack``; `coherent_jax.study.carry`), so that a clone elsewhere continues it.
``--verify`` writes ``experiments/results/verify.json`` (`coherent_jax.study.verify`).

Exit status: 0 when every selected cell is done (with ``--verify``: bit-identical), 1 when
a cell's sweep failed (with ``--verify``: a cell differs or was not verified), 2 for bad
input (an unknown suite or cell, a refused results directory).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

# The package this script runs is this checkout's, whatever else is installed (a worktree's
# results are made and tabulated by its own code, as its cells' subprocesses are).
ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]
from coherent_jax.study import command, spec, verify  # noqa: E402
from coherent_jax.study.cell import Cell, StudyError  # noqa: E402

STUDIES = ROOT / "experiments" / "studies"
RESULTS = ROOT / "experiments" / "results"
SUITES = ("smoke", "thesis", "ablations", "beyond", "sparse", "protocol", "classic")


def study_file(suite: str) -> Path:
    if suite not in SUITES:
        raise StudyError(f"unknown suite {suite!r} (allowed: {', '.join(SUITES)})")
    return STUDIES / f"{suite}.yaml"


def load(suite: str, results: Path = RESULTS) -> spec.Study:
    """The suite's study, its folder ``results/SUITE``."""
    path = study_file(suite)
    data = {**spec.read_file(path), "out": str(Path(results) / suite)}
    return spec.make_study(data, path.parent, suite)


def select(suite: str, patterns: Sequence[str], results: Path = RESULTS) -> list[Cell]:
    """The suite's cells whose name matches one of `patterns` (all without any)."""
    return command.select(load(suite, results).cells(), patterns, suite)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python experiments/reproduce.py", description=__doc__.split("\n")[0]
    )
    parser.add_argument("suite", help=f"one of: {', '.join(SUITES)}")
    parser.add_argument("--status", action="store_true", help="print the state of each cell and exit")
    parser.add_argument("--cells", nargs="*", default=[], help="only cells whose name matches (glob)")
    parser.add_argument("--results", default=str(RESULTS), help="results directory (one folder per suite)")
    parser.add_argument("--pack", action="store_true", help="write each stopped cell's carry.tar.gz and exit")
    parser.add_argument("--commit", action="store_true", help="git-commit each finished cell's kept files")
    parser.add_argument(
        "--verify", nargs="*", metavar="CELL", help="re-run finished cells' first iterations at HEAD"
    )
    parser.add_argument("--iterations", type=int, default=verify.DEFAULT_ITERATIONS, help="with --verify")
    args = parser.parse_args(argv)
    results = Path(args.results).resolve()
    try:
        if results.exists() and not results.is_dir():
            raise StudyError(
                f"invalid value for '--results': {args.results!r} is not a directory "
                "(allowed: a results directory, existing or to be made)"
            )
        path = study_file(args.suite)
    except StudyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    patterns = [*args.cells, *(args.verify or [])]
    items = [
        str(path),
        f"out={results / args.suite}",
        *([f"cells=[{','.join(patterns)}]"] if patterns else []),
    ]
    if args.verify is not None:
        try:
            cells = select(args.suite, patterns, results)
        except StudyError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        how = f"python experiments/reproduce.py {args.suite} --verify {{cell}}"
        return verify.run(cells, results / args.suite, args.iterations, record=results, cwd=ROOT, command=how)
    flags = [f"{k}=true" for k in ("status", "pack", "commit") if getattr(args, k)]
    return command.main([*items, *flags])


if __name__ == "__main__":
    sys.exit(main())
