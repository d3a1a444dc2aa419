"""Reproduce the thesis's comparisons: ``python experiments/reproduce.py SUITE``.

A *cell* is one (task, algorithm, strategy, settings) run for N seeds as one vmapped
sweep (``python -m coherent_jax.sweep ... seeds=N``). Every cell of a suite is run in
turn; a cell's results land in ``experiments/results/SUITE/CELL/``:

* ``cell.json``: the cell's specification (overrides, seeds) and its fingerprint;
* ``sweep/``: the sweep's directory (one run directory per seed with ``config.yaml``,
  ``metrics.jsonl``, ``summary.json``, ``versions.json``; ``sweep.json`` once finished);
* ``run.log``: the sweep's output.

Cells are resumable: a cell whose sweep finished is never recomputed, one that was
stopped or killed continues from its checkpoint (``resume=``), and a results directory
written for another version of the cell's specification is refused rather than mixed
in. ``--status`` prints, for each cell, whether it is done, running, stopped or
missing, and the compute it still needs.

    python experiments/reproduce.py thesis --status
    nohup python experiments/reproduce.py thesis > reproduce-thesis.log 2>&1 &
    python experiments/reproduce.py ablations --cells 'halfcheetah/ppo/*'

Exit status: 0 when every selected cell is done, 1 when a cell's sweep failed,
2 for bad input (an unknown suite or cell, a refused results directory).
"""

from __future__ import annotations

import argparse
import dataclasses
import fnmatch
import hashlib
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results"
SPEC_VERSION = 1  # bump when the meaning of a cell's overrides changes

# The thesis's comparisons (chapter 4; its chapter 5 is not in our copy): A2C and PPO
# with each exploration strategy on the standard locomotion tasks.
THESIS_TASKS = ("halfcheetah", "walker2d", "hopper")
ONPOLICY_STRATEGIES = ("action", "coherent", "noisynet", "psne")
SAC_STRATEGIES = ("action", "coherent", "psne")
BEYOND_STRATEGIES = ("gsde", "pink")
ABLATION_TASK = "halfcheetah"
ABLATION_BETAS = (0.0, 0.01, 0.1, 0.5, 1.0)
DEFAULT_BETA = 0.01  # coherent_jax.config.Config.beta: the thesis cells' chain coefficient

# Exploration where rewards are rare (issue: sparse-reward tasks): PPO with every
# strategy on four sparse DeepMind Control tasks (Playground's ports), coherent at
# three beta from trajectory-based towards step-based, 1M env steps per seed.
# Cart-pole and acrobot run on MJX (Playground's own env); ball-in-cup and finger on
# native MuJoCo (`coherent_jax.envs.dmc_native`, 1.5x MJX's rate in PPO, pinned below).
SPARSE_TASKS = (
    "dmc-cartpole_swingup_sparse",
    "dmc-acrobot_swingup_sparse",
    "dmc-ball_in_cup",
    "dmc-finger_turn_hard",
)
SPARSE_STRATEGIES = ("action", "noisynet", "psne", "gsde", "pink")
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

# Rough env steps/s of one point, used by --status when no cell of the same task and
# algorithm has finished yet
# (docs/benchmarks.md: PPO 64 envs on native physics; coherent about 0.3-0.5x of it).
# SAC's figure is at UTD 1 and scales with 1 / utd_ratio (measured above).
DEFAULT_RATE = {"ppo": 6000.0, "a2c": 8000.0, "sac": 150.0}
# Tasks whose own rate differs from the locomotion tasks' (PPO, action noise, measured).
TASK_RATE = {
    "dmc-cartpole_swingup_sparse": 22000.0,
    "dmc-acrobot_swingup_sparse": 20000.0,
    "dmc-ball_in_cup": 19000.0,  # native MuJoCo (physics=auto on a CPU); 11.9k on MJX
    "dmc-finger_turn_hard": 25000.0,  # native; 17.3k on MJX
}
# A2C/PPO iteration time relative to action noise. SAC's strategies cost about the same
# as its action noise (HalfCheetah, one seed: coherent 0.93x, psne 1.05x): its updates
# dominate, and they do not depend on the strategy.
STRATEGY_COST = {"coherent": 2.5, "noisynet": 1.5, "psne": 2.2, "gsde": 1.3, "pink": 1.1}


@dataclasses.dataclass(frozen=True)
class Cell:
    """One (task, algorithm, strategy, settings) run for ``seeds`` seeds as one sweep."""

    suite: str
    name: str
    overrides: tuple[str, ...]
    seeds: int

    def spec(self) -> dict[str, Any]:
        return {
            "version": SPEC_VERSION,
            "suite": self.suite,
            "name": self.name,
            "overrides": list(self.overrides),
            "seeds": self.seeds,
        }

    @property
    def fingerprint(self) -> str:
        return hashlib.sha256(json.dumps(self.spec(), sort_keys=True).encode()).hexdigest()[:16]

    def setting(self, key: str, default: str | None = None) -> str | None:
        for item in reversed(self.overrides):
            k, _, v = item.partition("=")
            if k == key:
                return v
        return default

    @property
    def env_steps(self) -> int:
        """Env steps of the whole cell (every seed and every grid point)."""
        points = self.seeds
        for item in self.overrides:
            _, _, v = item.partition("=")
            if v.startswith("[") and not v.startswith("[["):
                if item.split("=", 1)[0] not in ("policy_hidden", "value_hidden"):
                    points *= len(v.strip("[]").split(","))
        return int(self.setting("total_steps", "0")) * points


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
        # The thesis's gradient (the default, coherent.gradient=exact: each segment's belief
        # re-filtered under the current parameters) against the stored belief's.
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
    return [
        _cell("beyond", task, algo, s, seeds=SEEDS)
        for task in THESIS_TASKS
        for algo in ("ppo", "a2c")
        for s in BEYOND_STRATEGIES
    ]


def sparse_cells() -> list[Cell]:
    betas = "[" + ",".join(f"{b:g}" for b in SPARSE_BETAS) + "]"
    cells = []
    for task in SPARSE_TASKS:
        cells += [_cell("sparse", task, "ppo", s, seeds=SEEDS) for s in SPARSE_STRATEGIES]
        cells.append(_cell("sparse", task, "ppo", "coherent", f"beta={betas}", seeds=SEEDS, tag="beta"))
    return cells


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
    for full in (*thesis_cells(), *ablation_cells(), *beyond_cells(), *sparse_cells()):
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
    overrides the smoke cells keep (a grid's marked ``[]``). The ablation's cells at beta
    0, 0.1, 0.5 and 1 are one kind, the sparse suite's beta grid another."""
    kept = (o.partition("=") for o in cell.overrides if o.startswith(SMOKE_KEPT))
    keys = sorted({k + ("[]" if v.startswith("[") else "") for k, _, v in kept})
    return (cell.setting("algo") or "", cell.setting("explore") or "", *keys)


SUITES = {
    "smoke": smoke_cells,
    "thesis": thesis_cells,
    "ablations": ablation_cells,
    "beyond": beyond_cells,
    "sparse": sparse_cells,
}


class ReproduceError(ValueError):
    """Bad input: one line, exit status 2."""


def cell_dir(cell: Cell, results: Path) -> Path:
    return results / cell.suite / cell.name


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


def check_cell_dir(cell: Cell, results: Path) -> None:
    """Refuses a results directory written for another specification of the cell."""
    path = cell_dir(cell, results) / "cell.json"
    if not path.exists():
        return
    try:
        stored = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ReproduceError(f"unreadable cell record {str(path)!r}: {exc}") from None
    if stored.get("fingerprint") != cell.fingerprint:
        raise ReproduceError(
            f"results directory {str(path.parent)!r} holds cell {cell.name!r} of another specification "
            f"(stored {stored.get('spec')}, now {cell.spec()}); move it away to recompute the cell"
        )


# ------------------------------------------------------------------ state of a cell
def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def cell_state(cell: Cell, results: Path) -> str:
    """done | running | stopped | missing."""
    d = cell_dir(cell, results)
    if (d / "sweep" / "sweep.json").exists():
        return "done"
    lock = d / "running.pid"
    if lock.exists():
        try:
            if _pid_alive(int(lock.read_text().split()[0])):
                return "running"
        except (ValueError, IndexError, OSError):
            pass
    return "stopped" if (d / "sweep").exists() else "missing"


def _point_dirs(sweep_dir: Path) -> list[Path]:
    if not sweep_dir.is_dir():
        return []
    return sorted(p for p in sweep_dir.iterdir() if (p / "config.yaml").exists())


def progress(cell: Cell, results: Path) -> tuple[float, float | None]:
    """(fraction of env steps done, measured env steps/s of the whole cell or None)."""
    sweep = cell_dir(cell, results) / "sweep"
    if (sweep / "sweep.json").exists():
        return 1.0, _measured_rate(sweep)
    done = 0
    for point in _point_dirs(sweep):
        rows = point / "metrics.jsonl"
        if rows.exists():
            lines = [json.loads(x) for x in rows.read_text().splitlines() if x.strip()]
            done += max((r.get("env_steps", 0) for r in lines), default=0)
    return (done / cell.env_steps if cell.env_steps else 0.0), None


def _measured_rate(sweep: Path) -> float | None:
    """Env steps/s of the whole cell (all points together), as its sweep recorded it."""
    try:
        return float(json.loads((sweep / "sweep.json").read_text())["sweep_env_steps_per_s"])
    except (OSError, KeyError, TypeError, ValueError):
        return None


def _cost(cell: Cell) -> float:
    """Iteration time relative to action noise (1 for SAC, whose updates dominate)."""
    if cell.setting("algo", "ppo") == "sac":
        return 1.0
    return STRATEGY_COST.get(cell.setting("explore", "action") or "action", 1.0)


def _kind(cell: Cell) -> tuple[str | None, ...]:
    """What sets a cell's rate apart from its strategy: task, algorithm, SAC's UTD."""
    return (cell.setting("env"), cell.setting("algo", "ppo"), cell.setting("utd_ratio"))


def _finished_cells(results: Path) -> list[tuple[Cell, float]]:
    """Every finished cell under ``results`` (any suite) with its measured rate."""
    found = []
    for spec_file in sorted(results.glob("*/**/cell.json")):
        rate = _measured_rate(spec_file.parent / "sweep")
        if rate is None:
            continue
        try:
            spec = json.loads(spec_file.read_text())["spec"]
            cell = Cell(spec["suite"], spec["name"], tuple(spec["overrides"]), int(spec["seeds"]))
        except (OSError, KeyError, TypeError, ValueError):
            continue
        found.append((cell, rate))
    return found


def estimated_seconds(cell: Cell, results: Path) -> float:
    """Compute the cell still needs.

    From its own measured rate once it has one; else from the finished cells of the
    same task and algorithm (any suite), each rescaled by STRATEGY_COST to this cell's
    strategy (median over them); else from the defaults above. Vmapped points share
    the cores, so a cell's total rate is about one point's, whatever its points.
    """
    fraction, rate = progress(cell, results)
    if rate is None:
        kin = [
            r * _cost(other) / _cost(cell)
            for other, r in _finished_cells(results)
            if _kind(other) == _kind(cell)
        ]
        if kin:
            rate = statistics.median(kin)
        else:
            algo = cell.setting("algo", "ppo")
            base = TASK_RATE.get(cell.setting("env", ""), DEFAULT_RATE.get(algo, 5000.0))
            if algo == "sac":
                base /= float(cell.setting("utd_ratio", "1.0"))
            rate = base / _cost(cell)
    return (1.0 - fraction) * cell.env_steps / rate


def status(cells: Iterable[Cell], results: Path) -> str:
    lines, left = [], 0.0
    for cell in cells:
        state = cell_state(cell, results)
        fraction, _ = progress(cell, results)
        need = 0.0 if state == "done" else estimated_seconds(cell, results)
        left += need
        lines.append(
            f"{cell.name:44s} {state:8s} {100 * fraction:5.1f}%  "
            f"{cell.env_steps / 1e6:6.2f}M env steps  needs ~{need / 3600:6.2f} h"
        )
    lines.append(
        f"total still needed: ~{left / 3600:.1f} h on this machine (estimates until a cell finishes)"
    )
    return "\n".join(lines)


# ------------------------------------------------------------------ running a cell
def sweep_command(cell: Cell, results: Path) -> list[str]:
    sweep = cell_dir(cell, results) / "sweep"
    if sweep.exists():
        return [sys.executable, "-m", "coherent_jax.sweep", f"resume={sweep}"]
    return [
        sys.executable,
        "-m",
        "coherent_jax.sweep",
        *cell.overrides,
        f"seeds={cell.seeds}",
        f"run_dir={sweep}",
    ]


def run_cell(cell: Cell, results: Path, log=print) -> int:
    d = cell_dir(cell, results)
    check_cell_dir(cell, results)
    d.mkdir(parents=True, exist_ok=True)
    record = {
        "spec": cell.spec(),
        "fingerprint": cell.fingerprint,
        "command": " ".join(sweep_command(cell, results)),
    }
    if not (d / "cell.json").exists():
        (d / "cell.json").write_text(json.dumps(record, indent=2) + "\n")
    (d / "running.pid").write_text(f"{os.getpid()}\n")
    cmd = sweep_command(cell, results)
    log(f"[reproduce] {cell.suite} {cell.name}: {' '.join(cmd[1:])}")
    t0 = time.time()
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    try:
        with open(d / "run.log", "a") as out:
            code = subprocess.call(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
    finally:
        (d / "running.pid").unlink(missing_ok=True)
    log(f"[reproduce] {cell.name}: exit {code} after {time.time() - t0:.0f} s")
    return code


def commit_cell(cell: Cell, results: Path) -> None:
    """Commits a finished cell's results (checkpoints are ignored by experiments/results/.gitignore)."""
    d = cell_dir(cell, results)
    subprocess.run(["git", "-C", str(ROOT), "add", "--", str(d)], check=True)
    subprocess.run(
        ["git", "-C", str(ROOT), "commit", "-q", "-m", f"results: {cell.suite} {cell.name}", "--", str(d)],
        check=False,
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python experiments/reproduce.py", description=__doc__.split("\n")[0]
    )
    parser.add_argument("suite", help=f"one of: {', '.join(SUITES)}")
    parser.add_argument("--status", action="store_true", help="print the state of each cell and exit")
    parser.add_argument("--cells", nargs="*", default=[], help="only cells whose name matches (glob)")
    parser.add_argument("--results", default=str(RESULTS), help="results directory")
    parser.add_argument(
        "--commit", action="store_true", help="git-commit each cell's results when it finishes"
    )
    args = parser.parse_args(argv)
    results = Path(args.results).resolve()
    try:
        cells = select(args.suite, args.cells)
        for cell in cells:
            check_cell_dir(cell, results)
    except ReproduceError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.status:
        print(status(cells, results))
        return 0
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
    print(status(cells, results))
    if failed:
        print(f"[reproduce] failed: {', '.join(failed)} (see their run.log)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
