"""Method optuna of a study's ``tune:`` block: a TPE search per strategy with pruning on its
learning curve (Optuna, the optional extra ``optuna``: ``pip install -e ".[optuna]"``).

Each unit (a strategy's cell ``TASK/ALGO/LABEL`` before tuning, `coherent_jax.study.tune`)
has its own Optuna study in ``TASK/ALGO/LABEL@tune/optuna.db`` (SQLite). A trial is one
cell, ``TASK/ALGO/LABEL@tune/tNNN``: a sweep of the tuning seeds at the trial's values, run
by the study's executor like any cell. The units search side by side, one trial each at a
time (TPE learns from the trials before); every unit gets ``budget`` trials, complete or
pruned (a trial whose sweep failed is not counted, and the unit's search stops there).

* Sampler: TPE, seeded with `SAMPLER_SEED` plus the trial's number, so that a search
  stopped and continued draws what one that ran through draws; its first `startup`
  trials are drawn at random.
* Pruning: Optuna's median rule on the learning curve. While a trial's sweep runs, each
  evaluation that every tuning seed has logged is reported (the metric over the curve so
  far, mean over the seeds); a trial below the median of the earlier trials at the same
  evaluation, from its second evaluation on and once `startup` trials ended, is stopped
  (SIGTERM to its sweep: a local executor's) and counted as pruned.
* Resuming: a trial left running by a stopped study continues its sweep from its
  checkpoint and is scored as if it had run through; a trial whose sweep ended is scored.

``search.json`` beside the storage holds the unit's tuning specification: a folder
searched for another is refused, as a cell of another specification is.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO, Any

from coherent_jax.study import execute, tune
from coherent_jax.study.cell import (
    LOG,
    PID_FILE,
    Cell,
    StudyError,
    cell_dir,
    cell_state,
    prepare,
    running_pid,
)

SAMPLER_SEED = 0
STORAGE = "optuna.db"
SEARCH_RECORD = "search.json"
POLL_S = 1.0


def startup(budget: int) -> int:
    """Trials drawn at random before TPE models the others, and before pruning starts."""
    return min(10, max(1, budget // 4))


def _optuna():
    try:
        import optuna  # an optional extra: only method optuna loads it
    except ImportError:
        raise StudyError(
            f"invalid value for 'tune.method': optuna is not installed (allowed: {tune.OPTUNA_EXTRA}; "
            "or method: grid)"
        ) from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna


def search_dir(out: Path, unit: Cell) -> Path:
    """``STUDY_DIR/TASK/ALGO/LABEL@tune``: the unit's storage, record and trial cells."""
    return Path(out) / (unit.name + tune.SUFFIX)


def search_spec(spec: tune.Tune, unit: Cell) -> dict[str, Any]:
    """What ``search.json`` holds: the block and the unit's specification."""
    return {"tune": spec.spec(), "unit": unit.spec()}


def check_searches(spec: tune.Tune, units: Sequence[Cell], out: Path) -> None:
    """Refuses a unit's folder searched for another specification (another space, budget, ...)."""
    for unit in units:
        path = search_dir(out, unit) / SEARCH_RECORD
        if path.is_file() and json.loads(path.read_text()) != search_spec(spec, unit):
            raise StudyError(
                f"results directory {str(path.parent)!r} holds the tuning of cell {unit.name!r} of another "
                "specification; move it away to tune it again"
            )


def distributions(optuna, dims: Mapping[str, tune.Dimension]) -> dict[str, Any]:
    """Optuna's distribution of each key: a range, or its values as categories (lists as text)."""
    out = {}
    for key, d in dims.items():
        if isinstance(d, tune.Range) and d.integer:
            out[key] = optuna.distributions.IntDistribution(d.low, d.high, log=d.log)
        elif isinstance(d, tune.Range):
            out[key] = optuna.distributions.FloatDistribution(float(d.low), float(d.high), log=d.log)
        else:
            choices = [tune.text(v) if isinstance(v, list | dict) else v for v in d]
            out[key] = optuna.distributions.CategoricalDistribution(choices)
    return out


def open_search(optuna, spec: tune.Tune, unit: Cell, out: Path):
    """The unit's Optuna study (made, or loaded to continue)."""
    d = search_dir(out, unit)
    d.mkdir(parents=True, exist_ok=True)
    record = d / SEARCH_RECORD
    if not record.is_file():
        record.write_text(json.dumps(search_spec(spec, unit), indent=1) + "\n")
    pruner = optuna.pruners.MedianPruner(n_startup_trials=startup(spec.budget), n_warmup_steps=1)
    return optuna.create_study(
        study_name=unit.name, storage=f"sqlite:///{d / STORAGE}", direction="maximize",
        load_if_exists=True, pruner=pruner,
    )  # fmt: skip


def counted(optuna, search) -> int:
    """The unit's trials that count toward its budget: complete or pruned."""
    states = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED)
    return len(search.get_trials(deepcopy=False, states=states))


@dataclasses.dataclass
class Active:
    """A trial whose sweep runs: its unit, trial, cell, the evaluations reported, whether pruned."""

    unit: Cell
    trial: Any
    cell: Cell
    reported: int = 0
    pruned: bool = False


def _next_trial(optuna, spec: tune.Tune, unit: Cell, search) -> tuple[Any, int] | None:
    """The trial the unit runs next and the evaluations it reported: one a stopped study left
    running, else a new one while the budget lasts (None when it is spent)."""
    running = search.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,))
    if running:
        return optuna.trial.Trial(search, running[0]._trial_id), len(running[0].intermediate_values)
    if counted(optuna, search) >= spec.budget:
        return None
    n = len(search.get_trials(deepcopy=False))
    search.sampler = optuna.samplers.TPESampler(seed=SAMPLER_SEED + n, n_startup_trials=startup(spec.budget))
    return search.ask(distributions(optuna, tune.keys_of(spec, unit.label, unit))), 0


def _report(spec: tune.Tune, active: Active, out: Path) -> None:
    """Reports the evaluations every tuning seed logged since the last; prunes below the median."""
    seeds = tune.seed_curves(out, active.cell)
    ready = min((len(c) for c in seeds), default=0) if len(seeds) == len(spec.seeds) else 0
    for k in range(active.reported, ready):
        active.trial.report(tune.mean_score([c[: k + 1] for c in seeds], spec.metric), k)
    active.reported = max(active.reported, ready)
    if ready and not active.pruned and active.trial.should_prune():
        active.pruned = stop_sweep(active.cell, out)


def stop_sweep(cell: Cell, out: Path) -> bool:
    """Stops a trial's sweep (SIGTERM: it checkpoints and ends); False where no process of this
    machine runs it (the trial then runs to its end)."""
    pid = running_pid(cell, out)
    if pid is None:
        return False
    os.kill(pid, signal.SIGTERM)
    return True


def _end(optuna, spec: tune.Tune, active: Active, search, out: Path, code: int) -> str:
    """Tells the search how the trial's sweep ended: pruned, complete (scored) or failed."""
    states = optuna.trial.TrialState
    if active.pruned:
        search.tell(active.trial.number, state=states.PRUNED)
        return "pruned"
    if cell_state(active.cell, out) == "done":  # a point that diverged scores -inf (exit 3)
        execute.finish_cell(active.cell, out)
        _report(spec, active, out)
        score = tune.mean_score(tune.seed_curves(out, active.cell), spec.metric)
        search.tell(active.trial.number, score)
        return f"{spec.metric} {score:.4g}"
    search.tell(active.trial.number, state=states.FAIL)
    return f"failed (exit {code}; see {cell_dir(active.cell, out) / LOG})"


def _start(spec: tune.Tune, unit: Cell, trial, reported: int, executor, out: Path, cwd: Path) -> Active:
    cell = tune.trial_cell(spec, unit, trial.number, trial.params)
    while running_pid(cell, out) is not None:  # a stopped study's sweep, checkpointing
        time.sleep(0.5)
    (cell_dir(cell, out) / PID_FILE).unlink(missing_ok=True)
    command = prepare(cell, out)
    d = cell_dir(cell, out)
    executor.start(execute.Job(cell, tuple(command), cwd, d / LOG, d / PID_FILE))
    return Active(unit, trial, cell, reported)


def run(study, executor, stream: IO[str] | None = None) -> list[str]:
    """Runs every unit's search to its budget; the names of the units whose search failed."""
    optuna = _optuna()
    spec, out, say = study.tune, study.out, (lambda line: print(line, file=stream or sys.stdout, flush=True))
    units = tune.units(spec, study.cells(tuned=False))
    searches = {u.name: open_search(optuna, spec, u, out) for u in units}
    pending, active, failed = list(units), {}, []
    try:
        while pending or active:
            for unit in [u for u in pending if u.name not in active]:
                if len(active) >= executor.slots:
                    break
                found = _next_trial(optuna, spec, unit, searches[unit.name])
                if found is None:
                    pending.remove(unit)
                    continue
                active[unit.name] = _start(spec, unit, *found, executor, out, study.base)
                say(f"[study] {active[unit.name].cell.name}: started {found[0].params}")
            for job, code in executor.wait(timeout=POLL_S):
                a = active.pop(job.cell.name.rsplit(tune.SUFFIX, 1)[0])
                how = _end(optuna, spec, a, searches[a.unit.name], out, code)
                say(f"[study] {a.cell.name}: {how}")
                if how.startswith("failed"):
                    pending.remove(a.unit)
                    failed.append(a.unit.name + tune.SUFFIX)
            for a in active.values():
                _report(spec, a, out)
    except KeyboardInterrupt:
        executor.stop()
        say("[study] stopped: the running trials checkpointed; the same command continues them")
        raise
    return failed


def results(study) -> list[dict[str, Any]]:
    """Each unit's trials (values, score, state) and the env steps they spent, for ``tune.json``."""
    optuna = _optuna()
    spec, out = study.tune, study.out
    found = []
    for unit in tune.units(spec, study.cells(tuned=False)):
        search = open_search(optuna, spec, unit, out)
        trials, spent = [], 0
        for t in search.get_trials(deepcopy=False):
            cell = tune.trial_cell(spec, unit, t.number, t.params)
            spent += tune.spent_steps(cell, out)
            score = t.value if t.value is not None and math.isfinite(t.value) else None
            trials.append({"values": dict(t.params), "score": score, "state": t.state.name.lower()})
        found.append({"unit": unit.name, "candidates": trials, "env_steps": spent})
    return found


def status_lines(study) -> list[str]:
    """Per unit: its trials complete, pruned, failed and running, of its budget."""
    optuna = _optuna()
    lines = []
    for unit in tune.units(study.tune, study.cells(tuned=False)):
        if not (search_dir(study.out, unit) / STORAGE).is_file():
            lines.append(f"{unit.name + tune.SUFFIX:44s} 0 of {study.tune.budget} trials")
            continue
        search = open_search(optuna, study.tune, unit, study.out)
        states = [t.state.name.lower() for t in search.get_trials(deepcopy=False)]
        n = sum(s in ("complete", "pruned") for s in states)
        parts = ", ".join(
            f"{states.count(s)} {s}" for s in ("complete", "pruned", "fail", "running") if s in states
        )
        lines.append(f"{unit.name + tune.SUFFIX:44s} {n} of {study.tune.budget} trials ({parts or 'none'})")
    return lines
