"""A new user's first hour (issue 48, rows 1-4 and 7): the README's commands and
snippets, the example and the messages, each as a new user meets them.

Every run here is the smallest that shows the behaviour: one or two iterations of the
`pointmass` test task with tiny networks, no learning checked.
"""

import importlib.util
import json
import re
import runpy
import shutil
import subprocess
import sys
import tomllib

import pytest
from helpers import ROOT, child_env

from coherent_jax import evaluate, plot, sweep
from coherent_jax.config import parse_overrides
from coherent_jax.config.checks import rounding_note
from coherent_jax.run.loop import eval_text
from coherent_jax.run.sweep import aggregate, format_table, parse_sweep

# One iteration of 2 envs x 4 steps, 8-unit networks, one evaluation episode of 8 steps.
TINY_SWEEP = [
    "env=pointmass",
    "num_envs=2",
    "unroll_length=4",
    "episode_length=8",
    "total_steps=8",
    "ppo.num_epochs=1",
    "ppo.num_minibatches=1",
    "eval_episodes=1",
    "policy_hidden=[8]",
    "value_hidden=[8]",
    "progress=false",
    "tensorboard=false",
]


@pytest.mark.slow
def test_row1_plot_takes_a_real_sweep_and_a_folder_of_sweeps_and_runs(tmp_path, capsys):
    """A sweep's root holds its own config.yaml beside grid.json: its points are the runs."""
    runs = tmp_path / "runs"
    sweep_dir = runs / "sweep"
    assert sweep.main([*TINY_SWEEP, "seeds=2", f"run_dir={sweep_dir}"]) == 0
    assert (sweep_dir / "config.yaml").is_file() and (sweep_dir / "grid.json").is_file()
    points = sorted(p for p in sweep_dir.iterdir() if p.is_dir())
    assert [p.name for p in points] == ["p000-seed=0", "p001-seed=1"]
    single = runs / "single"  # a run directory beside the sweep, as runs/ holds them
    shutil.copytree(points[0], single)
    capsys.readouterr()

    assert plot.main([str(sweep_dir), f"out={tmp_path / 'sweep-plots'}"]) == 0
    out = capsys.readouterr().out
    assert "2 runs, 1 task(s)" in out and " n=2 " in out, out
    assert (tmp_path / "sweep-plots" / "learning_curves.png").stat().st_size > 0

    assert plot.find_runs([runs]) == [single, *points]  # sorted: "single" < "sweep"
    assert plot.find_runs([runs, sweep_dir]) == [single, *points]  # each run once
    assert plot.main([str(runs), f"out={tmp_path / 'all-plots'}"]) == 0
    assert "3 runs, 1 task(s)" in capsys.readouterr().out

    empty = tmp_path / "empty"
    empty.mkdir()
    assert plot.main([str(empty)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(empty) in err[0] and "allowed" in err[0], err


def readme_python_blocks() -> list[str]:
    """The README's fenced ```python blocks, as written."""
    text = (ROOT / "README.md").read_text()
    return re.findall(r"^```python\n(.*?)^```$", text, flags=re.M | re.S)


@pytest.mark.slow
def test_row2_readme_python_snippets_run_as_written(tmp_path):
    """Each ```python block of the README runs unchanged, in a fresh directory, in seconds;
    the quickstart's ``action`` is the task's (pointmass: 2 numbers)."""
    blocks = readme_python_blocks()
    assert blocks, "the README has no ```python block"
    shapes = []
    for i, code in enumerate(blocks):
        assert "preset=" not in code and "total_steps=" in code, "a snippet must train a small budget"
        script = tmp_path / f"readme_{i}.py"
        script.write_text(code)
        # Runs the file as written, then reports the shape of the action it made, if any.
        show = (
            f"import runpy; ns = runpy.run_path({str(script)!r}); "
            "print(getattr(ns.get('action'), 'shape', None))"
        )
        proc = subprocess.run(
            [sys.executable, "-c", show],
            cwd=tmp_path,
            env=child_env(),
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        shapes.append(proc.stdout.strip().splitlines()[-1])
    assert "(2,)" in shapes, shapes  # the quickstart acts on the task
    assert list((tmp_path / "runs").iterdir()), "the snippet trained no run"


def load_example():
    spec = importlib.util.spec_from_file_location("train_and_act", ROOT / "examples" / "train_and_act.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_row3_example_runs_twice_each_in_a_fresh_run_dir(tmp_path, monkeypatch, capsys):
    """examples/train_and_act.py run twice: two run directories, no traceback; a named
    directory that holds a run is refused in one line, exit 2, and left as it was (the
    refusal runs the script as ``__main__`` in this process: it compiles nothing, and a
    third interpreter's start-up was most of its time)."""
    script = ROOT / "examples" / "train_and_act.py"
    example = [sys.executable, str(script), "--total-steps", "2048"]

    def run():
        return subprocess.run(
            example, cwd=tmp_path, env=child_env(), capture_output=True, text=True, timeout=300
        )

    for _ in range(2):
        proc = run()
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "4 episodes stepped from Python" in proc.stdout
    made = sorted((tmp_path / "runs").iterdir())
    assert len(made) == 2 and all(p.name.startswith("example-pointmass-") for p in made), made
    before = {p: p.read_bytes() for p in made[0].rglob("*") if p.is_file()}
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [str(script), "--total-steps", "2048", "--run-dir", str(made[0])])
    capsys.readouterr()
    with pytest.raises(SystemExit) as refused:
        runpy.run_path(str(script), run_name="__main__")
    err = capsys.readouterr().err.strip().splitlines()
    assert refused.value.code == 2 and len(err) == 1 and str(made[0]) in err[0], err
    assert {p: p.read_bytes() for p in made[0].rglob("*") if p.is_file()} == before

    fresh_run_dir = load_example().fresh_run_dir
    base = fresh_run_dir(tmp_path, stamp="T")
    base.mkdir()
    assert fresh_run_dir(tmp_path, stamp="T").name == "example-pointmass-T-2"


def test_row4_gymnasium_has_its_own_extra_named_wherever_it_is_needed():
    """`gym` holds gymnasium[mujoco] alone; `test` still has it; the messages and docs name
    ``pip install -e ".[gym]"``, and nothing sends a user to the test extra for Gymnasium."""
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert extras["gym"] == ["gymnasium[mujoco]==1.4.0"]
    assert "gymnasium[mujoco]==1.4.0" in extras["test"]
    command = 'pip install -e ".[gym]"'
    assert evaluate.GYMNASIUM_EXTRA == command
    assert command in (ROOT / "docs" / "runs.md").read_text()
    assert command in (ROOT / "coherent_jax" / "envs" / "gym_v5.py").read_text()
    texts = [*ROOT.glob("*.md"), *(ROOT / "docs").glob("*.md"), *(ROOT / "coherent_jax").rglob("*.py")]
    for path in texts:
        for paragraph in re.split(r"\n\s*\n", path.read_text()):
            if "gymnasium[mujoco]" in paragraph or "engine=gymnasium" in paragraph:
                assert '".[test]"' not in paragraph and "test extra" not in paragraph, (path, paragraph)
                assert "pip install gymnasium" not in paragraph, (path, paragraph)


def test_row7_progress_says_what_it_shows():
    """No eval=nan before the first evaluation; total_steps rounded up is said, with the
    steps it becomes; a sweep's spread is the sample sd, labelled, with its n."""
    assert eval_text({}) == "-"
    assert eval_text({"eval/episode_return": [1.0, 2.0]}) == "1.5"

    note = rounding_note(parse_overrides(["total_steps=50000"]))
    assert "total_steps=50000" in note and "53,248 env steps" in note and "13 iterations" in note
    assert rounding_note(parse_overrides(["total_steps=40960"])) is None  # 10 x 64 x 64

    plan = parse_sweep([*TINY_SWEEP, "seeds=2", "lr=[1e-3,3e-4]"])
    summaries = [
        {"lr": 1e-3, "final_eval_return": 111.45},
        {"lr": 1e-3, "final_eval_return": 73.80},
        {"lr": 3e-4, "final_eval_return": 5.0},
        {"lr": 3e-4, "final_eval_return": None},
    ]
    rows = aggregate(plan, summaries)
    assert rows[0]["final_eval_return_std"] == pytest.approx(26.6225, abs=1e-4)  # ddof 1
    assert rows[1]["final_eval_return_std"] is None  # one finite seed has no sd
    table = format_table(plan, rows)
    assert "mean ± sd" in table and "sample sd" in table
    assert "92.6 ± 26.6 (n=2)" in table and "5.0 (n=1)" in table, table
    json.dumps(rows)  # sweep.json still takes them
