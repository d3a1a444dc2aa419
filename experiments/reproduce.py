"""Reproduce the thesis's comparisons: ``python experiments/reproduce.py SUITE``.

A *cell* is one (task, algorithm, strategy, settings) run for N seeds as one vmapped
sweep (``python -m coherent_jax.sweep ... seeds=N``). Every cell of a suite is run in
turn; a cell's results land in ``experiments/results/SUITE/CELL/``:

* ``cell.json``: the cell's specification (overrides, seeds) and its fingerprint;
* ``sweep/``: the sweep's directory (one run directory per point with ``config.yaml``,
  ``metrics.jsonl``, ``summary.json``; ``versions.json``; ``sweep.json`` once finished);
* ``run.log``: the sweep's output.

When a cell finishes, the curves the report reads go to its suite's table
``experiments/results/SUITE/curves.csv.gz`` (`curves.py`). Git keeps that table and
the cell's small files (``--commit`` commits exactly these); the per-seed
``metrics.jsonl``, ``run.log`` and TensorBoard files stay where the cell ran
(``experiments/results/.gitignore``). A cell present only as the kept files, as in a
clone, is done.

Cells are resumable: a cell whose sweep finished is never recomputed, one that was
stopped or killed continues from its checkpoint (``resume=``), and a results directory
written for another version of the cell's specification is refused rather than mixed
in. ``--status`` prints, for each cell, whether it is done, running, stopped, carried or
missing, and the compute it still needs. ``--pack`` writes each stopped cell's state
to its ``carry.tar.gz`` (`carry`), which git keeps, so that a clone elsewhere continues
it: a cell longer than a machine is kept still finishes (stop it with SIGTERM first,
which checkpoints it).

    python experiments/reproduce.py thesis --status
    nohup python experiments/reproduce.py thesis > reproduce-thesis.log 2>&1 &
    python experiments/reproduce.py ablations --cells 'halfcheetah/ppo/*'
    python experiments/reproduce.py protocol --pack --commit
    nohup python experiments/reproduce.py classic --commit > reproduce-classic.log 2>&1 &
    python experiments/reproduce.py thesis --verify 'hopper/ppo/*'   # does HEAD still compute them?

``--verify``: "bit-identical" or "differs from iteration N" per finished cell (`verify`).

Exit status: 0 when every selected cell is done (with ``--verify``: bit-identical), 1 when
a cell's sweep failed (with ``--verify``: a cell differs or was not verified),
2 for bad input (an unknown suite or cell, a refused results directory).
"""

from __future__ import annotations

import argparse
import fnmatch
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

# experiments/ is a folder of scripts, not a package: its modules import each other by name.
# The package they read is this checkout's, whatever else is installed (a worktree's
# results are made and tabulated by its own code, as its cells' subprocesses are).
ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "experiments"), str(ROOT)]
import carry  # noqa: E402
import curves  # noqa: E402
import verify  # noqa: E402
from cells import (  # noqa: E402, F401  (re-exported: the state of a cell is read as reproduce.X)
    DEFAULT_RATE,
    EPISODE_GRADIENT_COST,
    SPEC_VERSION,
    STRATEGY_COST,
    TASK_RATE,
    Cell,
    ReproduceError,
    _finished_cells,
    _measured_rate,
    _point_dirs,
    cell_dir,
    cell_state,
    check_cell_dir,
    estimated_seconds,
    progress,
    run_cell,
    status,
    sweep_command,
)
from classic import classic_cells  # noqa: E402  (the classic suite: MountainCar, its budget)

from coherent_jax import strategies  # noqa: E402  (the registry's names, no JAX)

RESULTS = ROOT / "experiments" / "results"

# The thesis's comparisons (chapter 4; its chapter 5 is not in our copy): A2C and PPO
# with each exploration strategy on the standard locomotion tasks.
THESIS_TASKS = ("halfcheetah", "walker2d", "hopper")
ONPOLICY_STRATEGIES = ("action", "coherent", "noisynet", "psne")
SAC_STRATEGIES = tuple(s for s in ONPOLICY_STRATEGIES if "sac" in strategies.SUPPORTED_ALGOS[s])
# `beyond`: every other strategy of the registry beside the thesis's on the same tasks,
# each cell named by its label in the report (`report._label`: the cell name's last part).
BEYOND_STRATEGIES = tuple(s for s in strategies.EXPLORES if s not in ONPOLICY_STRATEGIES)
# Coloured noise for on-policy algorithms (Hollenstein, Martius, Piater, AAAI 2024): an
# exponent near 0.5 rather than pink's 1 suits PPO; its cells are tagged with it.
PINK_ONPOLICY_EXPONENT = 0.5
PINK_ONPOLICY_TAG = f"exp{PINK_ONPOLICY_EXPONENT:g}"
BEYOND_SAC_STRATEGIES = tuple(s for s in BEYOND_STRATEGIES if "sac" in strategies.SUPPORTED_ALGOS[s])
# The report's labels of the beyond cells, the strategies the thesis's are compared with.
BEYOND_LABELS = (*BEYOND_STRATEGIES, f"pink-{PINK_ONPOLICY_TAG}")
ABLATION_TASK = "halfcheetah"
ABLATION_BETAS = (0.0, 0.01, 0.1, 0.5, 1.0)
DEFAULT_BETA = 0.01  # coherent_jax.config.Config.beta: the thesis cells' chain coefficient

# Exploration where rewards are rare (issue: sparse-reward tasks): PPO with every
# strategy on four sparse DeepMind Control tasks (Playground's ports), coherent at
# three beta from trajectory-based towards step-based, 1M env steps per seed.
# Cart-pole and acrobot run on MJX (Playground's own env); ball-in-cup and finger on
# native MuJoCo (`coherent_jax.envs.native_ports`, 1.5x MJX's rate in PPO, pinned below).
SPARSE_TASKS = (
    "dmc-cartpole_swingup_sparse",
    "dmc-acrobot_swingup_sparse",
    "dmc-ball_in_cup",
    "dmc-finger_turn_hard",
)
# Every PPO strategy of the registry; coherent runs as the beta sweep of `sparse_cells`.
SPARSE_STRATEGIES = tuple(
    s for s in strategies.EXPLORES if s != "coherent" and "ppo" in strategies.SUPPORTED_ALGOS[s]
)
SPARSE_BETAS = (0.0, 0.01, 0.1)
SPARSE_STEPS = 1_000_000

SEEDS = 5
ONPOLICY_STEPS = 1_000_000
# SAC with [256, 256] networks, 5 seeds vmapped at UTD 0.25 on HalfCheetah: 610 env
# steps/s over all seeds, about 150 seed-updates/s (two other cells running beside it;
# `python -m coherent_jax.sweep env=halfcheetah algo=sac seeds=5 utd_ratio=0.25
# total_steps=15000`). 1M steps for 5 seeds at UTD 1 would take about 9 hours per cell,
# 81 for the nine. We keep SAC's own settings and cut the budget to 200k steps at UTD
# 0.25 (50k updates per seed): about 35 minutes per cell.
SAC_STEPS = 200_000
SAC_SETTINGS = ("utd_ratio=0.25",)

# A2C/PPO settings per task, the same for every strategy (issue: credible baselines).
# HalfCheetah keeps the defaults (action-noise PPO: 3,691 at 1M steps over 5 seeds,
# between CleanRL's and RL Zoo's published figures). On Hopper the defaults stall near
# 370 at 0.5M steps (2 seeds): the value loss of unscaled returns dominates the shared
# gradient-norm clip and 80 minibatch steps per 4,096 env steps are few (CleanRL takes
# 320 per 2,048). Reward scaling and 32 minibatches (2 envs x 64 steps, 320 steps per
# iteration) are what SB3 and CleanRL use there (pilot runs: experiments/README.md).
ONPOLICY_TASK_SETTINGS: dict[str, tuple[str, ...]] = {
    "hopper": ("normalize_rewards=true", "num_minibatches=32"),
    "walker2d": ("normalize_rewards=true", "num_minibatches=32"),
    # Native MuJoCo, named so that a cell means the same engine on any machine.
    "dmc-ball_in_cup": ("physics=native",),
    "dmc-finger_turn_hard": ("physics=native",),
}

# A2C takes one gradient step per iteration (Algorithm 1: 4,096 env steps per step, 244
# steps in 1M): at the default lr 3e-4 action-noise A2C reached 469 on HalfCheetah and
# Coherent-A2C did not move (-2.5; 5 seeds each). At 3e-3 (1 seed each) they reached
# 1,935 and 1,580: the step size, not the method, had stalled them. Every A2C cell takes
# it (as tests/test_pairs.py and tests/test_train.py do).
A2C_SETTINGS = ("lr=0.003",)


def _cell(suite: str, task: str, algo: str, explore: str, *extra: str, seeds: int, tag: str = "") -> Cell:
    steps = SAC_STEPS if algo == "sac" else ONPOLICY_STEPS
    overrides = [f"env={task}", f"algo={algo}", f"explore={explore}", f"total_steps={steps}"]
    if algo == "sac":
        overrides += SAC_SETTINGS
    else:
        overrides += ONPOLICY_TASK_SETTINGS.get(task, ())
    if algo == "a2c":
        overrides += A2C_SETTINGS
    overrides += list(extra)
    name = f"{task}/{algo}/{explore}" + (f"-{tag}" if tag else "")
    return Cell(suite, name, tuple(overrides), seeds)


def thesis_cells() -> list[Cell]:
    cells = []
    for task in THESIS_TASKS:
        for algo in ("ppo", "a2c"):
            cells += [_cell("thesis", task, algo, s, seeds=SEEDS) for s in ONPOLICY_STRATEGIES]
        cells += [_cell("thesis", task, "sac", s, seeds=SEEDS) for s in SAC_STRATEGIES]
    return cells


def ablation_cells() -> list[Cell]:
    """One cell per beta (5 seeds, 25-40 minutes each here), so that every cell fits in one
    stretch of work; the default beta (0.01) is the thesis suite's coherent cell, which
    the ablations share rather than run again."""
    cells = []
    for algo in ("ppo", "a2c"):
        cells += [
            _cell("ablations", ABLATION_TASK, algo, "coherent", f"beta={b:g}", seeds=SEEDS, tag=f"beta{b:g}")
            for b in ABLATION_BETAS
            if b != DEFAULT_BETA
        ]
        cells.append(
            _cell(
                "ablations", ABLATION_TASK, algo, "coherent", "coherent.integration=mc", seeds=SEEDS, tag="mc"
            )
        )
        cells.append(
            _cell(
                "ablations",
                ABLATION_TASK,
                algo,
                "coherent",
                "coherent.integration=mc",
                "coherent.layers=all",
                seeds=SEEDS,
                tag="mc-all",
            )
        )
        # The default (coherent.gradient=exact: the chain restarts at each segment start and
        # each segment is scored from the prior, the thesis's gradient of that chain)
        # against the stored belief's (the chain runs on; its belief held constant).
        cells.append(
            _cell(
                "ablations",
                ABLATION_TASK,
                algo,
                "coherent",
                "coherent.gradient=stored",
                seeds=SEEDS,
                tag="stored",
            )
        )
    return cells


def beyond_cells() -> list[Cell]:
    """Per task: A2C and PPO with each of `BEYOND_STRATEGIES` and with coloured noise at the
    on-policy exponent, then SAC (the thesis suite's SAC budget) with `BEYOND_SAC_STRATEGIES`."""
    cells = []
    for task in THESIS_TASKS:
        for algo in ("ppo", "a2c"):
            cells += [_cell("beyond", task, algo, s, seeds=SEEDS) for s in BEYOND_STRATEGIES]
            cells.append(
                _cell(
                    "beyond",
                    task,
                    algo,
                    "pink",
                    f"pink.exponent={PINK_ONPOLICY_EXPONENT:g}",
                    seeds=SEEDS,
                    tag=PINK_ONPOLICY_TAG,
                )
            )
        cells += [_cell("beyond", task, "sac", s, seeds=SEEDS) for s in BEYOND_SAC_STRATEGIES]
    return cells


def sparse_cells() -> list[Cell]:
    betas = "[" + ",".join(f"{b:g}" for b in SPARSE_BETAS) + "]"
    cells = []
    for task in SPARSE_TASKS:
        cells += [_cell("sparse", task, "ppo", s, seeds=SEEDS) for s in SPARSE_STRATEGIES]
        cells.append(_cell("sparse", task, "ppo", "coherent", f"beta={betas}", seeds=SEEDS, tag="beta"))
    return cells


# The thesis's own protocol (preset=thesis: Spinning Up's settings, 4 envs x 1,000 steps
# per iteration, the coherent chain drawn at each buffer's start and running through it
# across resets). No per-task settings: the preset is the protocol for every task.
PROTOCOL = ("preset=thesis",)
# SAC under the preset updates once per env step (UTD 1, batch 100) from one env: about
# four times the updates of the thesis suite's SAC cells per env step. At the thesis
# suite's 200k steps a cell of 5 seeds took 1.0 h (HalfCheetah, Intel Xeon, one other
# cell beside it); 1M would take about 5 h, longer than a machine is kept here, and an
# SAC cell cannot be carried to the next (`carry`: its checkpoint holds the replay
# buffer). Spinning Up's own benchmarks run 3M steps.
PROTOCOL_SAC_STEPS = 200_000
# The chain-length ablation: the library's defaults (64-step segments), the chain cut
# at every segment (exact: the thesis suite's coherent cells, shared), running through
# the episode with the exact gradient (episode), or with the stored belief (stored:
# halfcheetah's is the ablation suite's, shared).
CHAIN_TASKS = ("halfcheetah", "hopper")


def protocol_cells() -> list[Cell]:
    cells = []
    for task in THESIS_TASKS:
        for algo in ("ppo", "a2c"):
            cells += [_protocol_cell(task, algo, s) for s in ONPOLICY_STRATEGIES]
        cells += [_protocol_cell(task, "sac", s) for s in SAC_STRATEGIES]
    for algo in ("ppo", "a2c"):
        cells += [
            _protocol_cell(ABLATION_TASK, algo, "coherent", f"beta={b:g}", tag=f"beta{b:g}")
            for b in ABLATION_BETAS
            if b != DEFAULT_BETA
        ]
    for task in CHAIN_TASKS:
        cells.append(
            _cell(
                "protocol", task, "ppo", "coherent", "coherent.gradient=episode", seeds=SEEDS, tag="episode"
            )
        )
        if task != ABLATION_TASK:
            cells.append(
                _cell(
                    "protocol", task, "ppo", "coherent", "coherent.gradient=stored", seeds=SEEDS, tag="stored"
                )
            )
    return cells


def _protocol_cell(task: str, algo: str, explore: str, *extra: str, tag: str = "") -> Cell:
    steps = PROTOCOL_SAC_STEPS if algo == "sac" else ONPOLICY_STEPS
    overrides = [f"env={task}", f"algo={algo}", f"explore={explore}", f"total_steps={steps}", *PROTOCOL]
    name = f"{task}/{algo}/{explore}-thesis" + (f"-{tag}" if tag else "")
    return Cell("protocol", name, (*overrides, *extra), SEEDS)


# Smoke: every kind of cell once, on the analytic pointmass task at a tiny budget, so
# that CI exercises the whole machinery (sweep, resume, status) in about a minute.
SMOKE_SETTINGS = (
    "env=pointmass",
    "num_envs=4",
    "unroll_length=8",
    "num_minibatches=2",
    "episode_length=32",
    "eval_episodes=2",
    "eval_every=2",
    "checkpoint_every=2",
    "progress=false",
    "tensorboard=false",
)


SMOKE_KEPT = ("coherent.", "beta=")  # the overrides of a full cell its smoke cell keeps


def smoke_cells() -> list[Cell]:
    cells = []
    suites = (thesis_cells, ablation_cells, beyond_cells, sparse_cells, protocol_cells, classic_cells)
    for full in (c for suite in suites for c in suite()):
        algo, explore = full.setting("algo"), full.setting("explore")
        extra = [o for o in full.overrides if o.startswith(SMOKE_KEPT)]
        steps = (
            ["total_steps=128", "warmup_steps=32", "batch_size=16", "buffer_size=512"]
            if algo == "sac"
            else ["total_steps=128"]
        )
        overrides = (f"algo={algo}", f"explore={explore}", *SMOKE_SETTINGS, *steps, *extra)
        name = "pointmass/" + full.name.split("/", 1)[1]
        cell = Cell("smoke", name, overrides, 2)
        if all(smoke_kind(c) != smoke_kind(cell) for c in cells):
            cells.append(cell)
    return cells


def smoke_kind(cell: Cell) -> tuple[str, ...]:
    """What the smoke suite runs once: a cell's algorithm, strategy and the keys of the
    overrides the smoke cells keep (a grid's marked ``[]``, a ``coherent.`` option's with
    its value). The ablation's cells at beta
    0, 0.1, 0.5 and 1 are one kind, the sparse suite's beta grid another."""
    kept = (o.partition("=") for o in cell.overrides if o.startswith(SMOKE_KEPT))
    # A coherent option's value is a different code path (gradient=episode is not =stored).
    keys = sorted(
        {
            k + ("[]" if v.startswith("[") else f"={v}" if k.startswith("coherent.") else "")
            for k, _, v in kept
        }
    )
    return (cell.setting("algo") or "", cell.setting("explore") or "", *keys)


SUITES = {
    "smoke": smoke_cells,
    "thesis": thesis_cells,
    "ablations": ablation_cells,
    "beyond": beyond_cells,
    "sparse": sparse_cells,
    "protocol": protocol_cells,
    "classic": classic_cells,
}


def select(suite: str, patterns: Sequence[str]) -> list[Cell]:
    if suite not in SUITES:
        raise ReproduceError(f"unknown suite {suite!r} (allowed: {', '.join(SUITES)})")
    cells = SUITES[suite]()
    if not patterns:
        return cells
    chosen = [c for c in cells if any(fnmatch.fnmatchcase(c.name, p) for p in patterns)]
    unmatched = [p for p in patterns if not any(fnmatch.fnmatchcase(c.name, p) for c in cells)]
    if unmatched:
        raise ReproduceError(
            f"unknown cell {unmatched[0]!r} in suite {suite!r} (allowed: {', '.join(c.name for c in cells)})"
        )
    return chosen


# ------------------------------------------------------------------ running a cell
def commit_cell(cell: Cell, results: Path) -> None:
    """Commits a finished cell's compact results: its suite's curves table, updated from the
    cell's per-seed logs, and the cell's small files (`curves.committed_files`). The logs
    themselves stay local (experiments/results/.gitignore)."""
    table = curves.update_table(results, cell.suite, [cell.name])
    files = [str(f) for f in curves.committed_files(cell_dir(cell, results), table)]
    files += carry.drop(cell_dir(cell, results), ROOT)
    _git_commit(files, f"results: {cell.suite} {cell.name}")


def _git_commit(files: Sequence[str], message: str) -> None:
    subprocess.run(["git", "-C", str(ROOT), "add", "--", *files], check=True)
    subprocess.run(["git", "-C", str(ROOT), "commit", "-q", "-m", message, "--", *files], check=False)


def pack_cells(cells: Sequence[Cell], results: Path, commit: bool) -> int:
    """``--pack``: each stopped cell's carry file; none if a selected cell is running (exit 2).
    A cell that cannot be carried (too large: SAC) is named and passed over (exit 1)."""
    running = [c.name for c in cells if cell_state(c, results) == "running"]
    if running:
        print(
            f"error: cell {running[0]!r} is running (allowed: stopped cells; SIGTERM checkpoints it)",
            file=sys.stderr,
        )
        return 2
    packed, failed = [], 0
    for cell in (c for c in cells if cell_state(c, results) == "stopped"):
        try:
            packed.append(str(carry.pack(cell_dir(cell, results))))
        except carry.CarryError as exc:
            print(f"error: {exc}", file=sys.stderr)
            failed += 1
            continue
        size = Path(packed[-1]).stat().st_size / 1e6
        print(
            f"[reproduce] {cell.name}: {100 * progress(cell, results)[0]:.1f}% done, packed in {size:.2f} MB"
        )
    if commit and packed:
        _git_commit(packed, f"results: carry {len(packed)} stopped cells of {cells[0].suite}")
    return 1 if failed else 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python experiments/reproduce.py", description=__doc__.split("\n")[0]
    )
    parser.add_argument("suite", help=f"one of: {', '.join(SUITES)}")
    parser.add_argument("--status", action="store_true", help="print the state of each cell and exit")
    parser.add_argument("--cells", nargs="*", default=[], help="only cells whose name matches (glob)")
    parser.add_argument("--results", default=str(RESULTS), help="results directory")
    parser.add_argument(
        "--pack",
        action="store_true",
        help="write each stopped cell's carry.tar.gz (its checkpoint and logs, for git) and exit",
    )
    parser.add_argument(
        "--commit",
        action="store_true",
        help="git-commit each cell's compact results (small files, suite's curves table) when it "
        "finishes, or with --pack the carry files",
    )
    parser.add_argument(
        "--verify",
        nargs="*",
        metavar="CELL",
        help="re-run the first iterations of each finished cell (or those named, glob) at HEAD and "
        "compare them with the committed curves; writes RESULTS/verify.json",
    )
    parser.add_argument(
        "--iterations",
        type=int,
        default=verify.DEFAULT_ITERATIONS,
        help="with --verify: iterations re-run at least (default %(default)s)",
    )
    args = parser.parse_args(argv)
    results = Path(args.results).resolve()
    try:
        if results.exists() and not results.is_dir():
            raise ReproduceError(
                f"invalid value for '--results': {args.results!r} is not a directory "
                "(allowed: a results directory, existing or to be made)"
            )
        cells = select(args.suite, [*args.cells, *(args.verify or [])])
        for cell in cells:
            check_cell_dir(cell, results)
    except ReproduceError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.status:
        print(status(cells, results))
        return 0
    if args.pack:
        return pack_cells(cells, results, args.commit)
    if args.verify is not None:
        return verify.run(cells, results, args.iterations)
    failed = []
    for cell in cells:
        state = cell_state(cell, results)
        if state in ("done", "running"):
            print(f"[reproduce] {cell.name}: {state}, skipped")
            continue
        if run_cell(cell, results) != 0 or cell_state(cell, results) != "done":
            failed.append(cell.name)
        elif args.commit:
            commit_cell(cell, results)
        else:  # the suite's table all the same, for whoever commits the results later; no carry file
            curves.update_table(results, cell.suite, [cell.name])
            carry.drop(cell_dir(cell, results), ROOT)
    print(status(cells, results))
    if failed:
        print(f"[reproduce] failed: {', '.join(failed)} (see their run.log)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
