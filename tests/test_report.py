"""experiments/report.py (RESULTS.md) and the compact results it reads through the package
(`coherent_jax.study.curves`, `stats`, `tables`, `execute`): claims, verdicts, curves and what
`--commit` adds. Cells are laid out as finished sweeps write them; no training runs.
"""

import gzip
import json
import shutil
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from cell_fakes import fake_sweep, reproduce
from helpers import child_env, load_experiment

from coherent_jax.study import cost, curves, execute, stats, tables
from coherent_jax.study.cell import cell_state, progress

ROOT = Path(__file__).resolve().parents[1]


def _report():
    """experiments/report.py (it imports plotting and rliable on load, so only where needed)."""
    return load_experiment("report")


def test_report_counts_a_seed_as_reaching_the_sparse_reward_at_its_first_positive_return():
    from coherent_jax import plot

    report = _report()

    def run(values):
        steps = np.arange(1, len(values) + 1) * 4096
        return plot.Run(Path("."), "dmc-ball_in_cup", "ppo", "action", 0, steps, np.array(values), {})

    # No episode completed (NaN) and zero returns are not a hit; the first positive one is.
    assert report.reached_reward(run([np.nan, 0.0, 0.0, 3.0, 0.0, 7.0])) == 4 * 4096
    assert report.reached_reward(run([np.nan, 0.0, 0.0])) is None
    assert report.reached_reward(run([-1.0, 0.0])) is None


def test_report_pairs_each_claim_with_its_comparison():
    report = _report()
    assert ("beta=0.01", "psne") in report._pairs("sparse", {"beta=0.01": 0, "beta=0": 0, "psne": 0})
    assert ("coherent", "psne") in report._pairs("thesis", {"coherent": 0, "psne": 0})
    # The ablations' claims compare the coherent method with its variants: the thesis's three
    # components (the chain, analytic integration, last layer) and the exact gradient.
    labels = ["beta=0.01", "beta=0", "beta=1", "coherent-mc", "coherent-mc-all", "coherent-stored", "action"]
    ablation = report._pairs("ablations", dict.fromkeys(labels, 0))
    assert {("beta=0.01", "coherent-mc"), ("coherent-mc", "coherent-mc-all"), ("beta=0.01", "beta=1")} <= set(
        ablation
    )
    assert all("action" not in pair for pair in ablation)


def test_report_reads_ablations_and_beyond_beside_the_thesis_cells(tmp_path):
    report = _report()
    for name in ("halfcheetah/ppo/*", "hopper/a2c/coherent", "hopper/ppo/psne"):
        for cell in reproduce.select("thesis", [name]):
            fake_sweep(cell, tmp_path, finished=True)
    fake_sweep(reproduce.select("thesis", ["hopper/a2c/action"])[0], tmp_path, finished=False)
    names = lambda cells: sorted(c.name for c in cells)  # noqa: E731
    # Ablations: the thesis's action and coherent cells of the ablation task, finished ones only.
    ablations = reproduce.select("ablations", ["halfcheetah/ppo/*"])
    assert names(report._reference_cells("ablations", ablations, tmp_path)) == [
        "halfcheetah/ppo/action",
        "halfcheetah/ppo/coherent",
    ]
    # beyond: every finished thesis strategy of each task and algorithm gSDE or pink has run.
    beyond = reproduce.select("beyond", ["hopper/a2c/pink", "halfcheetah/ppo/gsde"])
    assert names(report._reference_cells("beyond", beyond, tmp_path)) == [
        "halfcheetah/ppo/action",
        "halfcheetah/ppo/coherent",
        "halfcheetah/ppo/noisynet",
        "halfcheetah/ppo/psne",
        "hopper/a2c/coherent",
    ]
    assert report._reference_cells("sparse", beyond, tmp_path) == []
    # Their verdicts: coherent against the newer strategies, not the thesis suite's again.
    labels = dict.fromkeys(["coherent", "action", "noisynet", "psne", "gsde", "pink"], 0)
    assert report._pairs("beyond", labels) == [("coherent", "gsde"), ("coherent", "pink")]
    labels.update({"lattice": 0, "pink-exp0.5": 0})
    assert report._pairs("beyond", labels) == [
        ("coherent", "gsde"),
        ("coherent", "pink"),
        ("coherent", "lattice"),
        ("coherent", "pink-exp0.5"),
    ]
    assert report.verdict({"p": 0.8, "low": 0.6, "high": 0.9}, "beyond") == "holds"


def test_report_reads_the_protocol_suite_as_three_comparisons(tmp_path):
    """Protocol cells lose their ``-thesis`` tag; the strategies, the beta ablation (with the
    coherent cell as beta 0.01) and the chain length (read beside the thesis suite's exact
    and the ablations' stored cells) are aggregated and claimed each among themselves."""
    report = _report()
    run = types.SimpleNamespace(settings={"coherent.beta": 0.5})
    label = {c.name: report._label(c, run, "protocol") for c in reproduce.select("protocol", [])}
    assert label["hopper/ppo/psne-thesis"] == "psne"
    assert label["walker2d/a2c/coherent-thesis"] == "coherent"
    assert label["halfcheetah/a2c/coherent-thesis-beta0.5"] == "beta=0.5"
    assert label["hopper/ppo/coherent-episode"] == "coherent-episode"
    exact = reproduce.select("thesis", ["hopper/ppo/coherent"])[0]
    assert report._label(exact, run, "protocol") == "coherent-exact"
    assert report._label(exact, run, "thesis") == "coherent"
    labels = ["action", "coherent", "psne", "beta=0", "beta=1", "coherent-episode", "coherent-exact"]
    assert report.label_groups("protocol", labels) == [
        ("", ["action", "coherent", "psne"]),
        ("beta ablation", ["beta=0", "beta=1", "coherent"]),
        ("chain length", ["coherent-episode", "coherent-exact"]),
    ]
    assert report.label_groups("thesis", ["psne", "action"]) == [("", ["action", "psne"])]
    pairs = report._pairs("protocol", dict.fromkeys(labels, 0))
    assert pairs == [
        ("coherent", "action"),
        ("coherent", "psne"),
        ("coherent", "beta=1"),
        ("coherent", "beta=0"),
        ("coherent-episode", "coherent-exact"),
    ]
    # The chain-length cells' references: only once one of them is done, finished ones only.
    assert report._reference_cells("protocol", [], tmp_path) == []
    for name in ("hopper/ppo/coherent", "halfcheetah/ppo/coherent"):
        fake_sweep(reproduce.select("thesis", [name])[0], tmp_path, finished=True)
    episode = reproduce.select("protocol", ["hopper/ppo/coherent-episode"])
    assert [c.name for c in report._reference_cells("protocol", episode, tmp_path)] == ["hopper/ppo/coherent"]


def test_report_aggregates_only_the_tasks_every_strategy_has_finished():
    report = _report()
    scores = {
        "action": {"hopper": np.array([1.0, 3.0]), "halfcheetah": np.array([10.0, 30.0])},
        "coherent": {"halfcheetah": np.array([20.0, 40.0])},
    }
    norm = report.normalised(scores)
    assert set(norm) == {"action", "coherent"}
    # One task in common, min-max over both strategies' runs of it.
    np.testing.assert_allclose(norm["action"], [[0.0], [2 / 3]])
    np.testing.assert_allclose(norm["coherent"], [[1 / 3], [1.0]])
    # The table says which task it aggregates and which it leaves out, and why.
    assert tables.aggregate_table("ppo", "final return", scores, norm)[0] == (
        "**ppo, final return**, normalised per task over 1 task(s)"
        " (halfcheetah; hopper left out until every strategy has finished it):"
    )
    assert report.normalised({"a": {"hopper": np.ones(2)}, "b": {"walker2d": np.ones(2)}}) == {}


# ------------------------------------------------------------------ compact results


def _fake_finished_cell(cell, results, seeds=2):
    """A finished cell as a sweep writes it: per point config.yaml, metrics.jsonl (returns
    as floats of every kind, rows logging neither, a partial last line), summary.json, and
    beside them the files that stay local (run.log, TensorBoard, a checkpoint)."""
    d = fake_sweep(cell, results, finished=True)
    (d / "sweep" / "seed=0").rename(d / "sweep" / "p000-seed=0")
    for seed in range(1, seeds):
        (d / "sweep" / f"p{seed:03d}-seed={seed}").mkdir()
    for seed in range(seeds):
        point = d / "sweep" / f"p{seed:03d}-seed={seed}"
        (point / "config.yaml").write_text(f"seed: {seed}\nenv: {cell.setting('env')}\n")
        rows = [
            {"iteration": 1, "env_steps": 4096, "train/episode_return": None},
            {"iteration": 2, "env_steps": 8192, "train/episode_return": 0.1 + 0.2 + seed},
            {"iteration": 3, "env_steps": 12288, "eval/episode_return": -2.5e-300, "train/episode_return": 0},
            {"iteration": 4, "env_steps": 16384, "eval/episode_return": 1234.5678901234567 * (seed + 1)},
            {"iteration": 5, "env_steps": 16384, "eval/episode_return": float("nan")},
        ]
        text = "".join(json.dumps(r) + "\n" for r in rows)
        (point / "metrics.jsonl").write_text(text + '{"iteration": 6, "env_st')  # killed mid-write
        (point / "summary.json").write_text(json.dumps({"seed": seed}))
        (point / "tb").mkdir()
        (point / "tb" / "events.out.tfevents.1").write_bytes(b"\0" * 64)
        (point / "checkpoint.msgpack").write_bytes(b"\0" * 64)
    for name in ("config.yaml", "grid.json", "sweep.csv", "versions.json"):
        (d / "sweep" / name).write_text("{}\n")
    (d / "run.log").write_text("progress bars\n")
    return d


def _runs(cells, results, metric):
    """What the report reads of `cells`: each point's name, seed, curve and settings."""
    return [
        (r.path.name, r.seed, r.steps.tolist(), r.values.tobytes(), r.settings)
        for c in cells
        for r in stats.load_runs(results / c.suite, c.name, metric)
    ]


def test_curves_table_round_trips_what_the_report_reads(tmp_path):
    report = _report()
    assert {report.METRIC, report.REACH_METRIC, *report.classic.GOAL_METRICS} == set(curves.METRICS)
    sparse_metrics = (report.METRIC, report.REACH_METRIC)  # the classic suite's: its own test
    cells = reproduce.select("sparse", ["dmc-ball_in_cup/ppo/action", "dmc-ball_in_cup/ppo/psne"])
    for cell in cells:
        _fake_finished_cell(cell, tmp_path)
    from_logs = {m: _runs(cells, tmp_path, m) for m in sparse_metrics}
    reach = [row for c in cells for row in report.reach_rows(c, tmp_path)]
    table = curves.build(tmp_path / "sparse")
    data = table.read_bytes()
    assert data[4:8] == b"\0\0\0\0"  # gzip without a time stamp
    # Rebuilding, or building in another order, gives the same bytes.
    curves.update_table(tmp_path / "sparse", [cells[1].name])
    assert table.read_bytes() == data
    table.unlink()
    for cell in reversed(cells):
        curves.update_table(tmp_path / "sparse", [cell.name])
    assert table.read_bytes() == data
    rows = curves.read_table(table)
    assert rows == sorted(rows, key=lambda r: r[:3]) and len(rows) == 2 * 2 * 4  # row 1 logged neither
    # Without the logs the report reads the same curves, bit for bit, from the table.
    for path in tmp_path.glob("sparse/**/metrics.jsonl"):
        path.unlink()
    assert {m: _runs(cells, tmp_path, m) for m in sparse_metrics} == from_logs
    assert [row for c in cells for row in report.reach_rows(c, tmp_path)] == reach
    # A finished cell whose logs are gone keeps its rows when the table is rebuilt.
    assert curves.build(tmp_path / "sparse").read_bytes() == data


def test_commit_adds_only_the_compact_files(tmp_path, monkeypatch):
    cell = reproduce.select("thesis", ["hopper/ppo/action"])[0]
    repo = tmp_path / "repo"
    results = repo / "experiments" / "results"
    d = _fake_finished_cell(cell, results)
    listed = curves.committed_files(d, curves.table_path(results / "thesis"))
    expected = [
        "cell.json",
        *(f"sweep/{f}" for f in ("config.yaml", "grid.json", "sweep.csv", "sweep.json", "versions.json")),
        *(f"sweep/p00{i}-seed={i}/{f}" for i in range(2) for f in ("config.yaml", "summary.json")),
    ]
    assert [p.relative_to(d).as_posix() for p in listed] == expected  # the table does not exist yet
    # experiments/results/.gitignore keeps exactly these (and the suite's table) out of the ignored.
    shutil.copy(ROOT / "experiments" / "results" / ".gitignore", results / ".gitignore")
    git = lambda *a: subprocess.run(["git", "-C", str(repo), *a], capture_output=True, text=True)  # noqa: E731
    if git("init", "-q").returncode != 0:
        pytest.skip("git is not available")
    files = [p.relative_to(repo).as_posix() for p in d.rglob("*") if p.is_file()]
    ignored = set(git("check-ignore", "--no-index", *files).stdout.split())
    assert sorted(set(files) - ignored) == sorted(p.relative_to(repo).as_posix() for p in listed)
    # --commit: the suite's table, updated from the cell's logs, and the cell's small files.
    for key, value in {"NAME": "test", "EMAIL": "test@example.com"}.items():
        monkeypatch.setenv(f"GIT_AUTHOR_{key}", value)
        monkeypatch.setenv(f"GIT_COMMITTER_{key}", value)
    execute.commit_cell(cell, results / "thesis")
    committed = git("show", "--name-only", "--format=%s", "HEAD").stdout.split("\n")
    assert committed[0] == "results: thesis hopper/ppo/action"
    prefix = "experiments/results/thesis/"
    assert sorted(filter(None, committed[1:])) == sorted(
        [prefix + "curves.csv.gz", *(f"{prefix}hopper/ppo/action/{f}" for f in expected)]
    )
    assert [r[:3] for r in curves.read_table(results / "thesis" / "curves.csv.gz")][:2] == [
        ("hopper/ppo/action", "p000-seed=0", 8192),
        ("hopper/ppo/action", "p000-seed=0", 12288),
    ]


def test_a_cell_present_only_as_compact_data_is_done(tmp_path):
    """A clone holds a finished cell's committed files only: it is done, needs nothing, and
    its measured rate still serves the estimates of the cells of its task and algorithm."""
    report = _report()
    done, missing = reproduce.select("thesis", ["hopper/a2c/action", "hopper/a2c/psne"])
    d = _fake_finished_cell(done, tmp_path / "ran")
    table = curves.update_table(tmp_path / "ran" / "thesis", [done.name])
    clone = tmp_path / "clone"
    for f in curves.committed_files(d, table):
        target = clone / f.relative_to(tmp_path / "ran")
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(f, target)
    assert not list(clone.rglob("metrics.jsonl")) and not list(clone.rglob("run.log"))
    assert cell_state(done, clone / "thesis") == "done"
    assert progress(done, clone / "thesis") == (1.0, 1000.0)
    assert cost.estimated_seconds(done, clone / "thesis") == 0.0
    assert [f.cell.name for f in cost.finished_cells(clone)] == [done.name]
    assert cost.estimated_seconds(missing, clone / "thesis") == pytest.approx(
        missing.env_steps * cost.STRATEGY_COST["psne"] / 1000.0
    )
    proc = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "reproduce.py"), "thesis", "--status", "--cells",
         "hopper/a2c/action", "--results", str(clone)],
        capture_output=True, text=True, timeout=60, env=child_env(),
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split()[:3] == ["hopper/a2c/action", "done", "100.0%"]
    assert len(report.cell_runs(done, clone)) == 2


def _fake_classic_cell(cell, results, reach: bool):
    """A finished classic cell of 2 seeds (per beta of a grid): returns and goal fractions as a
    sweep logs them; seeds that `reach` first reach the goal in training at 8,192 env steps
    and end with a policy that reaches it."""
    d = fake_sweep(cell, results, finished=True)
    shutil.rmtree(d / "sweep" / "seed=0")
    betas = [0.0, 0.01, 0.1] if cell.setting("explore") == "coherent" else [None]
    for i, (beta, seed) in enumerate((b, s) for b in betas for s in range(2)):
        point = d / "sweep" / f"p{i:03d}-seed={seed}"
        point.mkdir()
        extra = "" if beta is None else f"coherent:\n  beta: {beta}\n"
        explore = cell.setting("explore")
        text = f"seed: {seed}\nenv: mountain_car_continuous\nexplore: {explore}\n{extra}"
        (point / "config.yaml").write_text(text)
        hit = 1.0 if reach else 0.0
        rows = [
            {"env_steps": 4096, "train/episode_return": -30.0, "train/goal_reached": 0.0},
            {"env_steps": 8192, "train/episode_return": -5.0 + 80 * hit, "train/goal_reached": 0.5 * hit},
            {"env_steps": 12288, "train/goal_reached": None, "train/episode_return": None},
            {"env_steps": 12288, "eval/episode_return": 90.0 * hit - seed, "eval/goal_reached": hit},
        ]
        (point / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
        (point / "summary.json").write_text(json.dumps({"seed": seed}))


def test_classic_report_counts_the_seeds_that_reach_mountain_cars_goal(tmp_path, monkeypatch):
    """The classic suite's section: per strategy the seeds that reached the goal in training
    (and when first), the seeds whose final policy reaches it, and coherent's verdicts at each
    beta against the other strategies. Figures and bootstrap intervals are stubbed (minutes
    of work, tested elsewhere): the probability of improvement is the plain one."""
    report = _report()
    monkeypatch.setattr(report, "curve_figures", lambda *args: [])
    monkeypatch.setattr(tables, "aggregate_table", lambda *args: [])

    def plain_poi(x, y):
        p = float(np.mean(x[:, None, :] > y[None, :, :]))
        return {"p": p, "low": p, "high": p}

    monkeypatch.setattr(stats, "probability_of_improvement", plain_poi)
    for name, reach in (("*/ppo/action", False), ("*/ppo/pink", True), ("*/ppo/coherent-beta-episode", True)):
        _fake_classic_cell(reproduce.select("classic", [name])[0], tmp_path, reach)
    text = report.build(tmp_path, tmp_path / "RESULTS.md", ["classic"])
    assert "## Suite `classic`" in text
    assert "| action | 0 of 2 | - | 0 of 2 |" in text
    assert "| pink | 2 of 2 | 8,192 | 2 of 2 |" in text
    for beta in ("0", "0.01", "0.1"):
        assert f"| beta={beta} | 2 of 2 | 8,192 | 2 of 2 |" in text
    assert "classic, ppo, final return: beta=0 improves on action (1 task(s)) | 1.00" in text
    assert "| holds |" in text and "beta=0.1 improves on pink" in text
    # The curves table keeps the goal columns: without the logs the report reads the same.
    curves.update_table(tmp_path / "classic", [c.name for c in reproduce.select("classic", [])])
    for path in tmp_path.glob("classic/**/metrics.jsonl"):
        path.unlink()
    assert report.build(tmp_path, tmp_path / "RESULTS.md", ["classic"]) == text


def test_classic_curves_table_of_returns_only_still_reads(tmp_path):
    """A table written before the goal columns existed reads with empty goal fields."""
    legacy = "cell,point,env_steps,eval/episode_return,train/episode_return\nc,p,4096,,1.5\n"
    data = gzip.compress(legacy.encode(), mtime=0)
    assert curves.decode(data) == [("c", "p", 4096, None, 1.5, None, None)]
    with pytest.raises(ValueError, match="not a curves table"):
        curves.decode(gzip.compress(b"cell,point,env_steps,other\n"))
