"""The suites of experiments/studies/ (through experiments/reproduce.py), cell selection,
refusals, the state of a cell and the compute it still needs (`coherent_jax.study.cell`,
`coherent_jax.study.cost`).

These checks need no training: cells are read from the study files, and a cell's state is
read from files laid out as a sweep writes them.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from cell_fakes import fake_sweep, reproduce
from helpers import child_env, load_experiment

from coherent_jax.study import cost
from coherent_jax.study.cell import (
    Cell,
    StudyError,
    cell_dir,
    cell_state,
    check_cell_dir,
    progress,
    sweep_command,
)

ROOT = Path(__file__).resolve().parents[1]
THESIS_TASKS = ("halfcheetah", "walker2d", "hopper")


def test_thesis_suite_covers_every_comparison():
    names = {c.name for c in reproduce.select("thesis", [])}
    for task in ("halfcheetah", "walker2d", "hopper"):
        for algo in ("ppo", "a2c"):
            for s in ("action", "coherent", "noisynet", "psne"):
                assert f"{task}/{algo}/{s}" in names
        for s in ("action", "coherent", "psne"):
            assert f"{task}/sac/{s}" in names
    assert all(c.seeds >= 5 for c in reproduce.select("thesis", []))


def test_every_cell_is_a_valid_config_with_its_tasks_settings_for_every_strategy():
    """Every full-size cell parses as a training config (as the sweep will parse it), and the
    A2C/PPO cells of a task share that task's settings whatever the strategy."""
    from coherent_jax.config import parse_overrides
    from coherent_jax.run.sweep import parse_sweep

    cells = [c for s in ("thesis", "ablations", "beyond") for c in reproduce.select(s, [])]
    settings = reproduce.load("thesis").grids[0].task_settings
    assert settings == reproduce.load("beyond").grids[0].task_settings
    for cell in cells:
        cfg = parse_sweep([*cell.overrides, f"seeds={cell.seeds}"]).base
        task_settings = settings.get(cfg.env, {}).get(cfg.algo, ())
        if cfg.algo == "sac":
            assert not cfg.ppo.normalize_rewards, cell.name
        else:
            assert all(item in cell.overrides for item in task_settings), cell.name
        if cfg.algo == "a2c":  # one gradient step per iteration: its own step size
            assert cfg.lr == 3e-3, cell.name
    assert parse_overrides(["env=hopper", *settings["hopper"]["ppo"]]).ppo.normalize_rewards
    assert not settings.get("halfcheetah")  # the ablations' and done cells' defaults


def test_beyond_adds_lattice_onpolicy_pink_and_sac_cells_and_keeps_the_others():
    """Lattice and pink at the on-policy exponent 0.5 (a cell name of its own) for A2C and PPO,
    gSDE, pink and Lattice for SAC at the thesis suite's SAC budget; the first cells keep
    their specification (and so their stored results)."""
    cells = {c.name: c for c in reproduce.select("beyond", [])}
    thesis_sac = reproduce.select("thesis", ["hopper/sac/action"])[0]
    for task in THESIS_TASKS:
        for algo in ("ppo", "a2c"):
            assert cells[f"{task}/{algo}/lattice"].setting("explore") == "lattice"
            pink = cells[f"{task}/{algo}/pink-exp0.5"]
            assert (pink.setting("explore"), pink.setting("pink.exponent")) == ("pink", "0.5")
            assert cells[f"{task}/{algo}/pink"].setting("pink.exponent") is None
        for explore in ("gsde", "pink", "lattice"):
            sac = cells[f"{task}/sac/{explore}"]
            assert sac.overrides[3:] == thesis_sac.overrides[3:]  # total_steps and SAC's settings
    assert cells["halfcheetah/ppo/gsde"].overrides == (
        "env=halfcheetah",
        "algo=ppo",
        "explore=gsde",
        "total_steps=1000000",
    )
    assert len(cells) == len(THESIS_TASKS) * (2 * 4 + 3)
    assert "pink-exp0.5" in reproduce.load("beyond").labels()
    assert "lattice" in reproduce.load("sparse").labels()


def test_sparse_suite_runs_every_strategy_on_four_sparse_control_tasks():
    from coherent_jax.config import EXPLORES, SUPPORTED_ALGOS
    from coherent_jax.envs.registry import DMC_SPARSE_TASKS

    cells = reproduce.select("sparse", [])
    tasks = {c.setting("env") for c in cells}
    assert len(tasks) >= 4 and tasks <= set(DMC_SPARSE_TASKS)
    on_policy = {e for e in EXPLORES if "ppo" in SUPPORTED_ALGOS[e]}
    for task in tasks:
        mine = [c for c in cells if c.setting("env") == task]
        assert {c.setting("explore") for c in mine} == on_policy
        assert all(c.setting("algo") == "ppo" and c.seeds >= 5 for c in mine)
        (coherent,) = [c for c in mine if c.setting("explore") == "coherent"]
        assert len(coherent.setting("beta").strip("[]").split(",")) >= 3


def test_classic_suite_runs_every_strategy_on_mountain_car():
    """PPO with every on-policy strategy on MountainCarContinuous, 5 seeds each; coherent at beta
    0, 0.01 and 0.1 with the episode gradient (beta 0: one draw per episode); every cell a valid
    sweep; the budget's estimate 60-90 minutes."""
    classic = load_experiment("classic")

    from coherent_jax.config import EXPLORES, SUPPORTED_ALGOS
    from coherent_jax.run.sweep import parse_sweep

    cells = reproduce.select("classic", [])
    on_policy = {e for e in EXPLORES if "ppo" in SUPPORTED_ALGOS[e]}
    assert {c.setting("explore") for c in cells} == on_policy and len(cells) == len(on_policy)
    for cell in cells:
        task = ("mountain_car_continuous", "ppo", 5)
        assert (cell.setting("env"), cell.setting("algo"), cell.seeds) == task
        assert cell.setting("total_steps") == "200000"
        sweep = parse_sweep([*cell.overrides, f"seeds={cell.seeds}"])
        assert sweep.base.env == "mountain_car_continuous" and sweep.base.total_steps == 200_000
    (coherent,) = [c for c in cells if c.setting("explore") == "coherent"]
    assert coherent.setting("coherent.beta") == "[0,0.01,0.1]"
    assert coherent.setting("coherent.gradient") == "episode"
    assert coherent.env_steps == 15 * 200_000
    assert 60 <= classic.estimated_minutes() <= 90


def test_ablations_vary_one_component_each():
    from coherent_jax.config import Config

    cells = {c.name: c for c in reproduce.select("ablations", [])}
    # One cell of five seeds per beta; the default beta is the thesis suite's coherent cell.
    assert Config().coherent.beta == 0.01 and not any(c.setting("beta") == "0.01" for c in cells.values())
    thesis = {c.name: c for c in reproduce.select("thesis", [])}
    for algo in ("ppo", "a2c"):
        assert thesis[f"halfcheetah/{algo}/coherent"].setting("beta") is None
        betas = sorted(
            float(c.setting("beta"))
            for c in cells.values()
            if c.setting("algo") == algo and c.name.split("/")[2].startswith("coherent-beta")
        )
        assert betas == [0.0, 0.1, 0.5, 1.0]
    beta = cells["halfcheetah/ppo/coherent-beta0.5"]
    assert beta.setting("beta") == "0.5" and beta.env_steps == 5 * 1_000_000
    assert cells["halfcheetah/a2c/coherent-mc"].setting("coherent.integration") == "mc"
    assert cells["halfcheetah/ppo/coherent-mc-all"].setting("coherent.layers") == "all"
    for algo in ("ppo", "a2c"):
        stored = cells[f"halfcheetah/{algo}/coherent-stored"]
        assert stored.setting("coherent.gradient") == "stored" and stored.setting("beta") is None


def smoke_kind(cell: Cell) -> tuple[str, ...]:
    """What the smoke study runs once: a cell's algorithm, strategy and the keys of the
    overrides a smoke cell keeps (a grid's marked ``[]``, a ``coherent.`` option's with its
    value). The ablation's cells at beta 0, 0.1, 0.5 and 1 are one kind, the sparse suite's
    beta grid another."""
    kept = (o.partition("=") for o in cell.overrides if o.startswith(("coherent.", "beta=")))
    # A coherent option's value is a different code path (gradient=episode is not =stored).
    keys = sorted(
        {
            k + ("[]" if v.startswith("[") else f"={v}" if k.startswith("coherent.") else "")
            for k, _, v in kept
        }
    )
    return (cell.setting("algo") or "", cell.setting("explore") or "", *keys)


def test_suites_keep_the_cells_their_committed_results_were_made_for():
    """Every committed cell's ``cell.json`` fingerprint is its suite's cell's: the study files
    declare exactly the cells the results were computed for."""
    results = ROOT / "experiments" / "results"
    for suite in reproduce.SUITES:
        cells = {c.name: c for c in reproduce.select(suite, [])}
        for record in sorted((results / suite).glob("**/cell.json")):
            stored = json.loads(record.read_text())
            name = record.parent.relative_to(results / suite).as_posix()
            assert stored["fingerprint"] == cells[name].fingerprint, (suite, name)


def test_smoke_has_one_cell_per_kind_of_cell():
    smoke = reproduce.select("smoke", [])
    kinds = {smoke_kind(c) for c in smoke}
    suites = ("thesis", "ablations", "beyond", "sparse", "protocol", "classic")
    full = [c for s in suites for c in reproduce.select(s, [])]
    # Pointmass in place of each task, tiny budgets: the smoke kind of a full cell keeps
    # its algorithm, strategy, override keys and grids.
    assert {smoke_kind(c) for c in full} == kinds
    assert len(smoke) == len(kinds)
    assert all(c.setting("env") == "pointmass" for c in smoke)
    names = {c.name for c in smoke}
    assert {"pointmass/ppo/coherent-beta0", "pointmass/ppo/coherent-beta", "pointmass/sac/psne"} <= names
    assert {"pointmass/ppo/coherent-stored", "pointmass/ppo/coherent-episode"} <= names
    assert "pointmass/ppo/coherent-beta-episode" in names  # the classic suite's coherent grid
    (grid,) = [c for c in smoke if c.name == "pointmass/ppo/coherent-beta"]
    assert grid.setting("beta").startswith("[")


def test_fingerprint_changes_with_the_specification():
    a = Cell("thesis", "x/ppo/action", ("env=x", "algo=ppo"), 5)
    assert a.fingerprint == Cell("thesis", "x/ppo/action", ("env=x", "algo=ppo"), 5).fingerprint
    assert a.fingerprint != Cell("thesis", "x/ppo/action", ("env=x", "algo=ppo", "lr=1"), 5).fingerprint
    assert a.fingerprint != Cell("thesis", "x/ppo/action", ("env=x", "algo=ppo"), 6).fingerprint


def test_selection_by_glob_and_unknown_names():
    chosen = reproduce.select("thesis", ["hopper/ppo/*"])
    assert [c.name for c in chosen] == [f"hopper/ppo/{s}" for s in ("action", "coherent", "noisynet", "psne")]
    with pytest.raises(StudyError, match="unknown suite 'paper'.*allowed: smoke"):
        reproduce.select("paper", [])
    with pytest.raises(StudyError, match="unknown cell 'ant/\\*'.*halfcheetah/ppo/action"):
        reproduce.select("thesis", ["ant/*"])


def test_estimates_read_cells_of_the_same_preset_and_strategy_first(tmp_path):
    """A protocol cell (``preset=thesis``: 4 envs x 1,000 steps) takes no rate from a cell
    at the defaults; a finished cell of the same strategy is taken as it ran."""
    (cell,) = reproduce.select("protocol", ["hopper/a2c/psne-thesis"])
    costs = cost.STRATEGY_COST
    default = cell.env_steps * costs["psne"] / cost.DEFAULT_RATE["a2c"]
    # The thesis suite's hopper/a2c/psne ran at the defaults: not this cell's kind.
    fake_sweep(reproduce.select("thesis", ["hopper/a2c/psne"])[0], tmp_path, finished=True)
    assert cost.estimated_seconds(cell, tmp_path / cell.suite) == pytest.approx(default)
    # A protocol cell of the same task and algorithm, another strategy: rescaled.
    fake_sweep(reproduce.select("protocol", ["hopper/a2c/action-thesis"])[0], tmp_path, finished=True)
    assert cost.estimated_seconds(cell, tmp_path / cell.suite) == pytest.approx(
        cell.env_steps * costs["psne"] / 1000.0
    )
    # The ablation suite's coherent cells are of the thesis suite's coherent cell's kind and
    # strategy: their rate (set to 400) is taken as it is, the action cell (1,000) left aside.
    (coherent,) = reproduce.select("thesis", ["halfcheetah/ppo/coherent"])
    fake_sweep(reproduce.select("thesis", ["halfcheetah/ppo/action"])[0], tmp_path, finished=True)
    assert cost.estimated_seconds(coherent, tmp_path / coherent.suite) == pytest.approx(
        coherent.env_steps * costs["coherent"] / 1000.0
    )
    beta0 = fake_sweep(reproduce.select("ablations", ["halfcheetah/ppo/coherent-beta0"])[0], tmp_path, True)
    (beta0 / "sweep" / "sweep.json").write_text(json.dumps({"sweep_env_steps_per_s": 400.0}))
    expected = coherent.env_steps / 400.0
    assert cost.estimated_seconds(coherent, tmp_path / coherent.suite) == pytest.approx(expected)
    # The episode gradient is a strategy of its own cost: the coherent cell's rate (400)
    # divided by EPISODE_GRADIENT_COST, not taken as it is.
    (episode,) = reproduce.select("protocol", ["halfcheetah/ppo/coherent-episode"])
    fake_sweep(coherent, tmp_path, finished=True)
    (cell_dir(coherent, tmp_path / coherent.suite) / "sweep" / "sweep.json").write_text(
        json.dumps({"sweep_env_steps_per_s": 400.0})
    )
    assert cost.estimated_seconds(episode, tmp_path / episode.suite) == pytest.approx(
        episode.env_steps * cost.EPISODE_GRADIENT_COST / 400.0
    )


def test_a_started_cell_is_estimated_from_its_own_logged_rate(tmp_path):
    """A stopped or running cell's points log env steps and time: their rates (first to
    last logged iteration, the first one's compilation left out) add up to the cell's and
    come before any other cell's; a point without times leaves the estimate to the others."""
    (episode,) = reproduce.select("protocol", ["halfcheetah/ppo/coherent-episode"])
    coherent = reproduce.select("thesis", ["halfcheetah/ppo/coherent"])[0]
    fake_sweep(coherent, tmp_path, finished=True)  # 1,000 env steps/s, rescaled otherwise
    d = fake_sweep(episode, tmp_path, finished=False)
    total = int(episode.setting("total_steps"))
    rows = [(total // 8, 80.0), (total // 4, 100.0), (total // 2, 100.0 + (total // 4) / 20.0)]
    for seed in (0, 1):
        point = d / "sweep" / f"seed={seed}"
        point.mkdir(exist_ok=True)
        (point / "config.yaml").write_text(f"seed: {seed}\n")
        lines = [{"iteration": i, "env_steps": n, "time_s": t} for i, (n, t) in enumerate(rows)]
        (point / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    fraction, rate = progress(episode, tmp_path / episode.suite)
    assert fraction == pytest.approx(2 * 0.5 / episode.seeds)
    # Each point: (total/2 - total/8) env steps in (total/4)/20 + 20 s.
    point_rate = (total // 2 - total // 8) / ((total // 4) / 20.0 + 20.0)
    assert rate == pytest.approx(2 * point_rate)
    assert cost.estimated_seconds(episode, tmp_path / episode.suite) == pytest.approx(
        (1 - fraction) * episode.env_steps / (2 * point_rate)
    )
    # One point without times: the finished coherent cell's rate, rescaled, again.
    (d / "sweep" / "seed=1" / "metrics.jsonl").write_text(json.dumps({"env_steps": total // 2}) + "\n")
    assert progress(episode, tmp_path / episode.suite)[1] is None
    assert cost.estimated_seconds(episode, tmp_path / episode.suite) == pytest.approx(
        (1 - fraction) * episode.env_steps * cost.EPISODE_GRADIENT_COST / 1000.0
    )


def test_estimates_read_cells_of_this_cpu_model_first(tmp_path, monkeypatch):
    """Rates differed about twofold between CPUs: a finished cell of this machine's CPU
    model is read before any other, even of another strategy; unknown CPUs are others."""
    (cell,) = reproduce.select("protocol", ["hopper/a2c/psne-thesis"])
    monkeypatch.setattr(cost, "cpu_info", lambda: {"cpu_model": "This CPU"})

    def finished(suite, name, overrides, rate, cpu):
        d = fake_sweep(Cell(suite, name, overrides, cell.seeds), tmp_path, finished=True)
        (d / "sweep" / "sweep.json").write_text(json.dumps({"sweep_env_steps_per_s": rate}))
        if cpu is not None:
            (d / "sweep" / "versions.json").write_text(json.dumps({"cpu_model": cpu}))

    # The same strategy and kind, run elsewhere (another CPU, and one of unknown CPU).
    finished("elsewhere", "psne-a", cell.overrides, 500.0, "Other CPU")
    finished("elsewhere", "psne-b", cell.overrides, 700.0, None)
    assert cost.estimated_seconds(cell, tmp_path / cell.suite) == pytest.approx(cell.env_steps / 600.0)
    # An action-noise cell of the same kind on this CPU: read first, rescaled.
    (action,) = reproduce.select("protocol", ["hopper/a2c/action-thesis"])
    finished(action.suite, action.name, action.overrides, 1000.0, "This CPU")
    expected = cell.env_steps * cost.STRATEGY_COST["psne"] / 1000.0
    assert cost.estimated_seconds(cell, tmp_path / cell.suite) == pytest.approx(expected)


def test_cell_states_and_compute_left(tmp_path):
    done, stopped, running, missing = reproduce.select("thesis", ["hopper/a2c/*"])
    fake_sweep(done, tmp_path, finished=True)
    fake_sweep(stopped, tmp_path, finished=False)
    d = fake_sweep(running, tmp_path, finished=False)
    (d / "running.pid").write_text(f"{os.getpid()}\n")
    assert cell_state(done, tmp_path / done.suite) == "done"
    assert cell_state(stopped, tmp_path / stopped.suite) == "stopped"
    assert cell_state(running, tmp_path / running.suite) == "running"
    assert cell_state(missing, tmp_path / missing.suite) == "missing"
    # One point of five has run half of its steps: a tenth of the cell.
    assert progress(stopped, tmp_path / stopped.suite)[0] == pytest.approx(0.5 / 5)
    assert cost.estimated_seconds(done, tmp_path / done.suite) == 0.0
    # Compute left: the stopped cell's nine tenths, the missing one's all, each at the
    # finished hopper/a2c/action cell's measured 1,000 env steps/s rescaled by its
    # strategy's cost (coherent 2.5x, psne 2.2x).
    costs = cost.STRATEGY_COST
    assert (stopped.setting("explore"), missing.setting("explore")) == ("coherent", "psne")
    assert cost.estimated_seconds(stopped, tmp_path / stopped.suite) == pytest.approx(
        0.9 * stopped.env_steps * costs["coherent"] / 1000.0
    )
    assert cost.estimated_seconds(missing, tmp_path / missing.suite) == pytest.approx(
        missing.env_steps * costs["psne"] / 1000.0
    )
    # With nothing finished of the same task and algorithm, the defaults.
    nothing = tmp_path / "nothing-run"
    default = missing.env_steps * costs["psne"] / cost.DEFAULT_RATE["a2c"]
    assert cost.estimated_seconds(missing, nothing / missing.suite) == pytest.approx(default)
    other = tmp_path / "other-task-run"
    fake_sweep(reproduce.select("thesis", ["halfcheetah/a2c/action"])[0], other, finished=True)
    fake_sweep(reproduce.select("thesis", ["hopper/ppo/action"])[0], other, finished=True)
    assert cost.estimated_seconds(missing, other / missing.suite) == pytest.approx(default)
    text = cost.status([done, stopped, running, missing], tmp_path / "thesis")
    assert "done" in text and "stopped" in text and "running" in text and "missing" in text
    # A stale lock (its process is gone) reads as stopped.
    (d / "running.pid").write_text("999999999\n")
    assert cell_state(running, tmp_path / running.suite) == "stopped"
    # A stopped cell resumes its sweep; a missing one starts it.
    assert any(a.startswith("resume=") for a in sweep_command(stopped, tmp_path / stopped.suite))
    assert any(a.startswith("run_dir=") for a in sweep_command(missing, tmp_path / missing.suite))


def test_a_cell_not_started_also_costs_its_start_compile_and_evaluations(tmp_path, monkeypatch):
    """The time left counts what a small cell mostly is: its sweep's seconds besides
    training, from finished cells of its kind (this CPU's first), else the defaults; nothing
    once the cell has started."""
    monkeypatch.setattr(cost, "cpu_info", lambda: {"cpu_model": "This CPU"})
    action, coherent, stopped, missing = reproduce.select("thesis", ["hopper/a2c/*"])
    assert cost.start_seconds(missing, tmp_path / missing.suite) == cost.DEFAULT_START_S["a2c"]
    other = reproduce.select("thesis", ["hopper/ppo/action"])[0]  # another kind, same study
    d = fake_sweep(other, tmp_path, finished=True)
    (d / "sweep" / "sweep.json").write_text(
        json.dumps({"sweep_env_steps_per_s": 1.0, "wall_s": 9.0, "train_s": 1.0})
    )
    assert cost.start_seconds(missing, tmp_path / missing.suite) == pytest.approx(8.0)

    def finished(cell, wall, train, cpu):
        d = fake_sweep(cell, tmp_path, finished=True)
        summary = {"sweep_env_steps_per_s": 1000.0, "wall_s": wall, "train_s": train}
        (d / "sweep" / "sweep.json").write_text(json.dumps(summary))
        (d / "sweep" / "versions.json").write_text(json.dumps({"cpu_model": cpu}))

    finished(action, 300.0, 250.0, "Other CPU")
    assert cost.start_seconds(missing, tmp_path / missing.suite) == pytest.approx(50.0)
    finished(coherent, 100.0, 70.0, "This CPU")  # this CPU's cells first
    assert cost.start_seconds(missing, tmp_path / missing.suite) == pytest.approx(30.0)
    fake_sweep(stopped, tmp_path, finished=False)
    assert cost.start_seconds(stopped, tmp_path / stopped.suite) == 0.0
    text = cost.status([missing], tmp_path / missing.suite)
    need = cost.estimated_seconds(missing, tmp_path / missing.suite) + 30.0
    assert f"needs ~{need / 3600:6.2f} h" in text


def test_results_of_another_specification_are_refused(tmp_path):
    cell = reproduce.select("thesis", ["hopper/ppo/action"])[0]
    d = fake_sweep(cell, tmp_path, finished=False)
    check_cell_dir(cell, tmp_path / cell.suite)  # its own results: accepted
    (d / "cell.json").write_text(json.dumps({"spec": {"seeds": 3}, "fingerprint": "0" * 16}))
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    proc = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "reproduce.py"), "thesis", "--cells", "hopper/ppo/action",
         "--results", str(tmp_path)],
        capture_output=True, text=True, timeout=60, env=child_env(),
    )  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "another specification" in proc.stderr
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_the_scripts_read_this_checkouts_package(tmp_path):
    """`reproduce.py` (and what it imports in-process: the curves table, the commit) reads
    the package of its own checkout, not another one earlier on the path (a worktree's
    results are made by its own code): a decoy ``coherent_jax`` on PYTHONPATH is not read."""
    decoy = tmp_path / "coherent_jax"
    decoy.mkdir()
    (decoy / "__init__.py").write_text("raise ImportError('the decoy package was imported')\n")
    code = (
        "import runpy, sys; runpy.run_path(sys.argv[1], run_name='loaded'); "
        "import coherent_jax.run.checkpoint; print(coherent_jax.run.checkpoint.__file__)"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(ROOT / "experiments" / "reproduce.py")],
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(tmp_path)),
        cwd=tmp_path,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert Path(proc.stdout.strip()).resolve().is_relative_to(ROOT / "coherent_jax")
