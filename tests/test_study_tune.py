"""A study's ``tune:`` block (`coherent_jax.study.tune`, `tune_run`, `optuna_search`): the block
read into tuning cells, every refusal (one line, exit status 2, nothing written: seeds that
overlap the evaluation's, a grid over the budget, an unknown key, a key a grid cannot vary,
optuna not installed), the choice and the report's section from stand-in results; marked slow,
a grid and an Optuna tuning on pointmass end to end, the evaluation cells at the values chosen.
"""

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import child_env

from coherent_jax.study import command, tune, tune_run

ROOT = Path(__file__).resolve().parents[1]

# Tiny cells: pointmass, 4 envs x 8 steps, 16-unit networks, no TensorBoard or progress bars.
SETTINGS = {
    "num_envs": 4, "unroll_length": 8, "ppo.num_minibatches": 2, "episode_length": 32,
    "policy_hidden": [16, 16], "value_hidden": [16, 16], "progress": False, "tensorboard": False,
}  # fmt: skip
STUDY = {
    "name": "tuned",
    "seeds": 2,
    "total_steps": 256,
    "tasks": ["pointmass"],
    "strategies": ["action", "coherent"],
    "settings": SETTINGS,
    "evaluation": {"episodes": 2, "every": 2},
    "tune": {
        "budget": 2,
        "seeds": 2,
        "total_steps": 128,
        "space": {"action": {"lr": [0.0003, 0.003]}, "coherent": {"beta": [0.0, 0.5]}},
    },
}


def _write(tmp_path: Path, **changes) -> Path:
    data = json.loads(json.dumps(STUDY))
    tuned = changes.pop("tune", {})
    data.update(changes)
    data["tune"].update(tuned)
    path = tmp_path / "tuned.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


# ------------------------------------------------------------------ the block and its cells
def test_the_block_makes_one_tuning_cell_per_strategy_on_seeds_apart(tmp_path):
    study, _, _ = command.parse([str(_write(tmp_path))])
    assert study.tune.method == "grid" and study.tune.metric == "auc" and not study.tune.per_task
    assert study.tune.seeds == (1000, 1001) and study.tune.budget == 2
    cells = {c.name: c for c in tune_run.cells(study)}
    assert list(cells) == ["pointmass/ppo/action@tune", "pointmass/ppo/coherent@tune"]
    beta = cells["pointmass/ppo/coherent@tune"]
    # One sweep: the grid (the key as it is now) x the tuning seeds, at the tuning's budget.
    assert beta.overrides[-3:] == ("total_steps=128", "seed=1000", "coherent.beta=[0.0,0.5]")
    assert beta.seeds == 2 and beta.env_steps == 2 * 2 * 128
    assert [o for o in beta.overrides if o.startswith("total_steps")] == ["total_steps=128"]
    # Before the tuning, the evaluation cells are the study's own; its choice is appended later.
    assert study.chosen is None and "coherent.beta" not in str(study.cells()[1].overrides)
    chosen = tune_run.dataclasses.replace(study, chosen={"pointmass/ppo/coherent": ("coherent.beta=0.5",)})
    assert chosen.cells()[1].overrides[-1] == "coherent.beta=0.5" and chosen.cells()[0] == study.cells()[0]
    # A strategy's own setting of a tuned key gives way to the tuned value (a sweep takes each key once).
    cell = tune.with_items(study.cells()[1], ["coherent.beta=0.1"])
    again = tune.with_items(cell, ["beta=0.5"])
    assert [o for o in again.overrides if "beta" in o] == ["beta=0.5"]


def _refused(tmp_path, capsys, path: Path, *extra: str) -> str:
    out = tmp_path / "studies"
    assert command.main([str(path), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ")
    assert not out.exists()  # nothing written
    return err


@pytest.mark.parametrize(
    "case, expected",
    [
        ({"tune": {"seed": 1}}, "tuning seeds 1..2 overlap the evaluation seeds 0..1"),
        ({"settings": {**SETTINGS, "seed": 999}}, "overlap the evaluation seeds 999..1000 of cell"),
        ({"tune": {"space": {"coherent": {"beta": [0.0, 0.1, 0.5]}}}}, "a grid of 3 candidates exceeds"),
        (
            {"tune": {"space": {"coherent": {"nosuch": [1, 2]}}}},
            "unknown key 'nosuch' in tune.space.coherent",
        ),
        ({"tune": {"space": {"coherent": {"seed": [1, 2]}}}}, "unknown key 'seed'"),
        ({"tune": {"space": {"pink": {"lr": [0.1]}}}}, "unknown strategy 'pink' in tune.space"),
        ({"tune": {"space": {"action": {"coherent.beta": [0.0, 0.1]}}}}, "explore=action cannot vary it"),
        ({"tune": {"space": {"action": {"lr": {"low": 0.001, "high": 0.01}}}}}, "a range with method grid"),
        ({"tune": {"space": {"coherent": {"beta": [0.0, 2.0]}}}}, "tune.space.coherent: invalid value"),
        ({"tune": {"method": "random"}}, "'tune.method': 'random' (allowed: grid, optuna)"),
        ({"tune": {"metric": "iqm"}}, "'tune.metric': 'iqm' (allowed: auc, final)"),
        ({"tune": {"trials": 3}}, "unknown key 'trials' in 'tune'"),
        ({"tune": {"seeds": 0}}, "'tune.seeds': 0 (allowed: an integer >= 1)"),
        ({"tune": {"space": {"coherent": {"beta": {"low": 1, "high": 0}}}}}, "tune.space.coherent.beta"),
        (
            {"tasks": ["pointmass", "pendulum"], "tune": {"method": "optuna"}},
            "'tune.per_task': false with method optuna and 2 tasks",
        ),
    ],
)
def test_a_bad_block_is_refused_in_one_line_before_anything_is_written(tmp_path, capsys, case, expected):
    err = _refused(tmp_path, capsys, _write(tmp_path, **case))
    assert expected in err, err


def test_a_key_a_grid_cannot_vary_is_refused_naming_it_and_optuna(tmp_path, capsys):
    space = {"action": {"lr": [0.001]}, "coherent": {"lr": [0.001]}, "pink": {"pink.exponent": [0.5, 1.0]}}
    path = _write(tmp_path, strategies=["action", "coherent", "pink"], tune={"space": space})
    err = _refused(tmp_path, capsys, path)
    assert "invalid key 'pink.exponent' in tune.space.pink with method grid" in err
    assert "method: optuna tunes any key" in err and "(allowed with grid: lr, gamma" in err


def test_optuna_not_installed_is_refused_naming_the_extra(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "optuna", None)  # its import fails, as where it is not installed
    space = {"action": {"lr": {"low": 0.0001, "high": 0.01, "log": True}}, "coherent": {"beta": [0.0, 0.5]}}
    err = _refused(tmp_path, capsys, _write(tmp_path, tune={"method": "optuna", "budget": 3, "space": space}))
    assert "optuna is not installed" in err and 'pip install -e ".[optuna]"' in err


def test_optuna_takes_ranges_and_keys_no_grid_can_vary(tmp_path):
    pytest.importorskip("optuna")
    space = {
        "action": {"lr": {"low": 0.0001, "high": 0.01, "log": True}},
        "pink": {"pink.exponent": [0.5, 1.5]},
    }
    path = _write(
        tmp_path, strategies=["action", "pink"], tune={"method": "optuna", "budget": 3, "space": space}
    )
    study, _, _ = command.parse([str(path)])
    command.spec.check(study, study.cells())
    assert study.tune.space["action"]["lr"] == tune.Range(0.0001, 0.01, True)
    assert tune_run.cells(study) == []  # trials are made as the search runs
    # A plan counts `budget` trials per strategy, at the space's first values.
    planned = tune_run.plan_cells(study)
    assert [c.name for c in planned][:3] == [f"pointmass/ppo/action@tune/t00{n}" for n in range(3)]
    assert len(planned) == 6 and "pink.exponent=0.5" in planned[-1].overrides


def test_the_docs_example_is_a_valid_study(tmp_path):
    text = (ROOT / "docs" / "study.md").read_text()
    (example,) = [b for b in re.findall(r"```yaml\n(.*?)```", text, flags=re.S) if "tune:" in b]
    (tmp_path / "tuned.yaml").write_text(example)
    study, _, _ = command.parse([str(tmp_path / "tuned.yaml")])
    command.spec.check(study, study.cells())
    assert [c.name for c in tune_run.cells(study)] == [
        "pointmass/ppo/action@tune",
        "pointmass/ppo/coherent@tune",
    ]
    assert study.tune.seeds == (1000, 1001) and tune.steps(study.tune, study.cells()[0]) == 50000


# ------------------------------------------------------------------ scores and the choice
def test_a_seeds_score_is_its_final_return_or_its_mean_over_training():
    curve = [(0, 0.0), (10, 10.0), (30, 10.0)]
    assert tune.seed_score(curve, "final") == 10.0
    assert tune.seed_score(curve, "auc") == pytest.approx((50 + 200) / 30)
    assert tune.seed_score(curve, "auc") == pytest.approx(np.trapezoid([0, 10, 10], [0, 10, 30]) / 30)
    assert tune.seed_score([], "auc") == -math.inf and tune.seed_score([(1, math.nan)], "final") == -math.inf
    assert tune.mean_score([curve, [(0, 2.0)]], "final") == 6.0
    assert tune.mean_score([curve, []], "final") == -math.inf  # a diverged seed sinks its candidate


def _unit(name: str, scores, states=None) -> dict:
    states = states or ["complete"] * len(scores)
    return {
        "unit": name,
        "candidates": [
            {"values": {"lr": v}, "score": s, "state": st}
            for v, s, st in zip((0.1, 0.2, 0.3), scores, states, strict=False)
        ],
    }


def test_the_choice_is_the_best_candidate_on_one_task_and_by_normalised_mean_on_several(tmp_path):
    space = {"action": {"lr": [0.1, 0.2, 0.3]}, "coherent": {"beta": [0.0, 0.5]}}
    path = _write(tmp_path, tasks=["pointmass", "pendulum"], tune={"budget": 3, "space": space})
    study, _, _ = command.parse([str(path)])
    units = tune.units(study.tune, study.cells(tuned=False))
    # Raw means favour lr=0.1 (pendulum's scale dominates); per-task normalised means favour 0.2.
    found = [
        _unit("pointmass/ppo/action", [0.0, 10.0, 9.0]),
        _unit("pendulum/ppo/action", [-100.0, -110.0, -300.0]),
    ]
    choices, chosen = tune_run.choose(study.tune, units, found)
    assert choices[0]["values"] == {"lr": 0.2} and choices[0]["tasks"] == ["pointmass", "pendulum"]
    assert chosen == {"pointmass/ppo/action": ["lr=0.2"], "pendulum/ppo/action": ["lr=0.2"]}
    # Per task: each task's best; a pruned trial and a diverged candidate are never chosen.
    per_task = tune_run.dataclasses.replace(study.tune, per_task=True)
    found[1] = _unit("pendulum/ppo/action", [-100.0, None, -1.0], ["complete", "complete", "pruned"])
    choices, chosen = tune_run.choose(per_task, units, found)
    assert chosen == {"pointmass/ppo/action": ["lr=0.2"], "pendulum/ppo/action": ["lr=0.1"]}


def test_the_report_states_the_protocol_the_budgets_and_flags_unequal_ones(tmp_path):
    record = {
        "method": "grid", "budget": 3, "seeds": [1000, 1001], "metric": "auc", "per_task": False,
        "evaluation_seeds": [0, 1, 2], "untuned": ["pink"],
        "units": [
            {**_unit("pointmass/ppo/action", [1.0, 2.0, 0.5]), "env_steps": 768, "steps": 128},
            {**_unit("pointmass/ppo/coherent", [3.0, None]), "env_steps": 512, "steps": 128},
        ],
        "choices": [
            {"label": "action", "algo": "ppo", "tasks": ["pointmass"], "values": {"lr": 0.2}, "score": 2.0},
            {"label": "coherent", "algo": "ppo", "tasks": ["pointmass"], "values": {"lr": 0.1}, "score": 3.0},
        ],
    }  # fmt: skip
    (tmp_path / tune_run.TUNE_FILE).write_text(json.dumps(record))
    text = "\n".join(tune_run.report_lines(tmp_path))
    assert "Tuning seeds 1000..1001; evaluation seeds 0..2: disjoint." in text
    assert "| pointmass/ppo/action@tune | 3 | 2 x 128 | 768 | `lr=0.2` | 2 |" in text
    unequal = "**Unequal budgets** (budget 3 candidates): pointmass/ppo/coherent ran 2 candidates"
    assert f"{unequal}; pink was not tuned." in text
    assert "| pointmass/ppo/coherent@tune | `lr=0.2` | -inf | complete |" in text
    assert "not done" in "\n".join(tune_run.report_lines(tmp_path / "nothing"))


# ------------------------------------------------------------------ Optuna's loop, with stand-in sweeps
EVALS = 4


class StandIn:
    """An executor whose sweeps write one evaluation per `wait` to each seed's log: a return
    that is higher the closer ``lr`` is to 1e-3 (and the same at every evaluation)."""

    slots = 2

    def __init__(self, out: Path, interrupt_at: int | None = None):
        self.out, self.interrupt_at, self.waits, self.jobs, self.stopped = out, interrupt_at, 0, {}, set()

    def start(self, job):
        sweep = self.out / job.cell.name / "sweep"
        first = int(job.cell.setting("seed"))
        for i in range(job.cell.seeds):
            point = sweep / f"p{i:03d}-seed={first + i}"
            point.mkdir(parents=True, exist_ok=True)
            (point / "config.yaml").write_text(f"seed: {first + i}\n")
            (point / "metrics.jsonl").touch()
        self.jobs[job.cell.name] = job

    def wait(self, timeout):
        self.waits += 1
        if self.waits == self.interrupt_at:
            raise KeyboardInterrupt
        ended = []
        for name, job in list(self.jobs.items()):
            if name in self.stopped:
                ended.append((job, 143))
                continue
            value = -10 * abs(math.log10(float(job.cell.setting("lr"))) + 3)
            points = sorted(p for p in (self.out / name / "sweep").iterdir() if p.is_dir())
            for point in points:
                k = len((point / "metrics.jsonl").read_text().splitlines()) + 1
                row = {"iteration": k, "env_steps": 32 * k, "eval/episode_return": value + k}
                with open(point / "metrics.jsonl", "a") as log:
                    log.write(json.dumps(row) + "\n")
            if k == EVALS:
                (self.out / name / "sweep" / "sweep.json").write_text("{}")
                ended.append((job, 0))
        for job, _ in ended:
            del self.jobs[job.cell.name]
        return ended

    def stop(self):
        self.jobs.clear()


def test_optunas_trials_are_pruned_on_the_curve_and_a_stopped_search_continues(tmp_path, monkeypatch):
    optuna = pytest.importorskip("optuna")
    from coherent_jax.study import optuna_search

    space = {"action": {"lr": {"low": 0.00001, "high": 0.1, "log": True}}}
    path = _write(tmp_path, strategies=["action"], tune={"method": "optuna", "budget": 8, "space": space})
    study, _, _ = command.parse([str(path)])
    study.out.mkdir(parents=True)
    first = StandIn(study.out, interrupt_at=3)  # the study stopped while its first trials run
    monkeypatch.setattr(optuna_search, "stop_sweep", lambda cell, out: first.stopped.add(cell.name) or True)
    with pytest.raises(KeyboardInterrupt):
        tune_run.run_stage(study, first)
    storage = f"sqlite:///{study.out}/pointmass/ppo/action@tune/optuna.db"
    search = optuna.load_study(study_name="pointmass/ppo/action", storage=storage)
    assert [t.state.name for t in search.trials] == ["RUNNING"]  # one trial at a time per strategy
    again = StandIn(study.out)
    monkeypatch.setattr(optuna_search, "stop_sweep", lambda cell, out: again.stopped.add(cell.name) or True)
    resolved, failed = tune_run.run_stage(study, again)
    assert failed == [] and resolved.chosen is not None
    trials = optuna.load_study(study_name="pointmass/ppo/action", storage=storage).trials
    # The stopped trial continued (not a new one): 8 trials, numbered 0 to 7, complete or pruned.
    assert [t.number for t in trials] == list(range(8))
    assert trials[0].params == search.trials[0].params and trials[0].state.name == "COMPLETE"
    assert sorted(trials[0].intermediate_values) == list(range(EVALS))
    pruned = [t for t in trials if t.state.name == "PRUNED"]
    assert pruned and all(len(t.intermediate_values) < EVALS for t in pruned)
    best = max((t for t in trials if t.state.name == "COMPLETE"), key=lambda t: t.value)
    assert resolved.chosen["pointmass/ppo/action"] == (f"lr={best.params['lr']}",)
    record = json.loads((study.out / tune_run.TUNE_FILE).read_text())
    assert [c["state"] for c in record["units"][0]["candidates"]] == [t.state.name.lower() for t in trials]


# ------------------------------------------------------------------ end to end
# Two strategies of one program (a sweepable key each): the test run's compilation cache
# compiles it for the tuning's points and for the evaluation's, not for each strategy.
ONE_PROGRAM = {"action": {}, "action-clip": {"explore": "action"}}


def _run(tmp_path: Path, path: Path, *extra: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "coherent_jax.study", str(path), "workers=2", *extra]
    done = subprocess.run(cmd, env=child_env(), capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def _auc(point: Path) -> float:
    """Independently of the package: the mean evaluation return over training, numpy's trapezoid."""
    rows = [json.loads(x) for x in (point / "metrics.jsonl").read_text().splitlines()]
    rows = [r for r in rows if r.get("eval/episode_return") is not None]
    steps = np.array([r["env_steps"] for r in rows], float)
    values = np.array([r["eval/episode_return"] for r in rows])
    return float(np.trapezoid(values, steps) / (steps[-1] - steps[0]))


@pytest.mark.slow
def test_a_grid_tuning_chooses_the_best_candidate_and_the_evaluation_runs_at_it(tmp_path, capsys):
    space = {"action": {"lr": [0.0003, 0.003]}, "action-clip": {"clip_eps": [0.1, 0.3]}}
    # 4 evaluation seeds, as many points as the tuning's 2 candidates x 2 seeds: one program for all.
    path = _write(tmp_path, seeds=4, strategies=ONE_PROGRAM, tune={"space": space})
    _run(tmp_path, path)
    out = tmp_path / "studies" / "tuned"
    record = json.loads((out / tune_run.TUNE_FILE).read_text())
    for label, key, group, name in (
        ("action", "lr", None, "lr"),
        ("action-clip", "ppo.clip_eps", "ppo", "clip_eps"),  # its flat key, as it is now
    ):
        sweep = out / "pointmass" / "ppo" / f"{label}@tune" / "sweep"
        points = sorted(p for p in sweep.iterdir() if (p / "metrics.jsonl").is_file())
        assert [p.name.split("-seed=")[1] for p in points] == ["1000", "1001"] * 2  # tuning seeds only
        means = {}
        for p in points:
            value = yaml.safe_load((p / "config.yaml").read_text())
            value = value[group][name] if group else value[name]
            means.setdefault(value, []).append(_auc(p))
        best = max(means, key=lambda v: np.mean(means[v]))
        (choice,) = [c for c in record["choices"] if c["label"] == label]
        assert choice["values"] == {key: best}
        # The evaluation cell ran its seeds 0 to 3 at the chosen value.
        evaluated = sorted((out / "pointmass" / "ppo" / label / "sweep").glob("p*"))
        assert [p.name.rsplit("=", 1)[1] for p in evaluated] == ["0", "1", "2", "3"]
        for p in evaluated:
            cfg = yaml.safe_load((p / "config.yaml").read_text())
            assert (cfg[group][name] if group else cfg[name]) == best
    assert record["evaluation_seeds"] == [0, 1, 2, 3] and record["seeds"] == [1000, 1001]
    assert all(u["env_steps"] == 2 * 2 * 128 for u in record["units"])
    again = _run(tmp_path, path)
    assert "tuning done" in again.stdout and "started" not in again.stdout
    # The report's section (study.json tells the report there is one); a changed choice is
    # refused as another specification of the cell.
    assert json.loads((out / "study.json").read_text())["tune"]["budget"] == 2
    report = "\n".join(tune_run.report_lines(out))
    assert "evaluation seeds 0..3: disjoint" in report and "| pointmass/ppo/action@tune | 2 |" in report
    record["chosen"]["pointmass/ppo/action-clip"] = ["ppo.clip_eps=0.25"]
    (out / tune_run.TUNE_FILE).write_text(json.dumps(record))
    capsys.readouterr()
    assert command.main([str(path)]) == 2
    assert "holds cell 'pointmass/ppo/action-clip' of another specification" in capsys.readouterr().err


@pytest.mark.slow
def test_an_optuna_tuning_runs_its_budget_per_strategy_and_continues_done(tmp_path):
    optuna = pytest.importorskip("optuna")
    space = {
        "action": {"lr": {"low": 0.0001, "high": 0.01, "log": True}},
        "action-clip": {"clip_eps": [0.1, 0.3]},
    }
    path = _write(tmp_path, strategies=ONE_PROGRAM, tune={"method": "optuna", "budget": 3, "space": space})
    first = _run(tmp_path, path, "cells=[pointmass/ppo/action]")  # one evaluation cell: a sweep less
    out = tmp_path / "studies" / "tuned"
    record = json.loads((out / tune_run.TUNE_FILE).read_text())
    assert [len(u["candidates"]) for u in record["units"]] == [3, 3]  # the same budget for each
    for label in ("action", "action-clip"):
        search = optuna.load_study(
            study_name=f"pointmass/ppo/{label}",
            storage=f"sqlite:///{out}/pointmass/ppo/{label}@tune/optuna.db",
        )
        trials = [t for t in search.trials if t.state.name in ("COMPLETE", "PRUNED")]
        assert len(trials) == 3 and all(t.intermediate_values for t in trials)
        assert (out / "pointmass" / "ppo" / f"{label}@tune" / "t002" / "sweep").is_dir()
        best = max((t for t in trials if t.state.name == "COMPLETE"), key=lambda t: t.value)
        (choice,) = [c for c in record["choices"] if c["label"] == label]
        assert choice["values"] == best.params
        assert f"{label} (ppo, pointmass): {best.params}" in first.stdout
    assert (out / "pointmass" / "ppo" / "action" / "sweep" / "sweep.json").is_file()
    again = _run(tmp_path, path, "cells=[pointmass/ppo/action]")
    assert "tuning done" in again.stdout and "started" not in again.stdout
