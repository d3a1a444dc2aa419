"""``python -m coherent_jax.study``: a study file and its command line, every refusal (one line,
exit status 2, nothing written), the executor's loop over cells (with stand-in sweeps), the
plan (it writes nothing but its cache), and, marked slow, a killed study continued to the same
results as an uninterrupted one.
"""

import ast
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import child_env

from coherent_jax.study import cell as study_cell
from coherent_jax.study import command, curves, execute, spec
from coherent_jax.study.cell import Cell, StudyError, cell_dir, cell_state

ROOT = Path(__file__).resolve().parents[1]
# Tiny cells: pointmass, 4 envs x 8 steps, 16-unit networks, no TensorBoard or progress bars.
TINY = (
    "num_envs=4", "unroll_length=8", "num_minibatches=2", "episode_length=32", "eval_episodes=2",
    "eval_every=2", "policy_hidden=[16,16]", "value_hidden=[16,16]", "progress=false", "tensorboard=false",
)  # fmt: skip
STUDY_FILE = """\
name: pusher
seeds: 3
total_steps: {ppo: 4096, sac: 1024}
tasks: [gym:Pusher-v5, pointmass]
algos:
  ppo: []
  sac: [sac.batch_size=16]
strategies:
  action: {}
  coherent: {}
  pink-0.5: {explore: pink, settings: [pink.exponent=0.5], algos: [ppo]}
  pink: {}
settings: [num_envs=4]
evaluation: {episodes: 2, every: 4}
metrics: [final, auc, reach]
compare: [coherent > action, coherent]
"""


def _tree(path: Path) -> list[str]:
    return sorted(p.relative_to(path).as_posix() for p in path.rglob("*"))


# ------------------------------------------------------------------ the study and its cells
def test_a_study_file_declares_its_cells_in_order_with_their_settings(tmp_path):
    (tmp_path / "pusher.yaml").write_text(STUDY_FILE)
    study, settings, _ = command.parse([str(tmp_path / "pusher.yaml")])
    assert study.name == "pusher" and study.out == tmp_path / "studies" / "pusher" and study.base == tmp_path
    cells = {c.name: c for c in study.cells()}
    assert list(cells)[:4] == [
        "Pusher-v5/ppo/action",
        "Pusher-v5/ppo/coherent",
        "Pusher-v5/ppo/pink-0.5",
        "Pusher-v5/ppo/pink",
    ]
    # A strategy twice under its own labels; the labelled one runs only with the algorithms it names.
    assert "pointmass/sac/pink" in cells and "pointmass/sac/pink-0.5" not in cells and len(cells) == 14
    assert cells["Pusher-v5/ppo/pink-0.5"].overrides == (
        "env=gym:Pusher-v5", "algo=ppo", "explore=pink", "total_steps=4096", "num_envs=4",
        "eval_episodes=2", "eval_every=4", "pink.exponent=0.5",
    )  # fmt: skip
    assert cells["pointmass/sac/coherent"].overrides[3:] == (
        "total_steps=1024", "num_envs=4", "eval_episodes=2", "eval_every=4", "sac.batch_size=16",
    )  # fmt: skip
    assert all(c.seeds == 3 and c.suite == "pusher" for c in cells.values())
    assert study.metrics == ("final", "auc", "reach")
    # "coherent" alone: against every other label, once each.
    assert [str(c) for c in study.comparisons] == [
        "coherent > action",
        "coherent > pink-0.5",
        "coherent > pink",
    ]
    assert settings["workers"] == 0 and not settings["plan"]


def test_the_command_line_is_a_study_and_overrides_a_files_keys(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    items = ["env=[gym:Pusher-v5,pointmass]", "explore=[action,coherent,pink]", "algo=ppo", "seeds=10",
             "total_steps=500000", "out=studies/pusher", "num_envs=16"]  # fmt: skip
    study, _, _ = command.parse(items)
    assert study.name == "pusher" and study.out == tmp_path / "studies" / "pusher"
    names = [c.name for c in study.cells()]
    assert names == [
        f"{t}/ppo/{s}" for t in ("Pusher-v5", "pointmass") for s in ("action", "coherent", "pink")
    ]
    first = study.cells()[0]
    assert first.overrides == (
        "env=gym:Pusher-v5",
        "algo=ppo",
        "explore=action",
        "total_steps=500000",
        "num_envs=16",
    )
    assert first.seeds == 10 and [str(c) for c in study.comparisons] == [
        "coherent > action",
        "coherent > pink",
    ]
    # With a file: the command line's keys win, its training items go to every cell.
    (tmp_path / "pusher.yaml").write_text(STUDY_FILE)
    study, settings, _ = command.parse(
        ["pusher.yaml", "seeds=2", "out=elsewhere", "lr=0.001", "--plan", "workers=3"]
    )
    assert (
        study.seeds == 2
        and study.out == tmp_path / "elsewhere"
        and settings["plan"]
        and settings["workers"] == 3
    )
    assert all("lr=0.001" in c.overrides for c in study.cells())
    # A registry variant is a strategy of its own name.
    (variant,) = command.parse(["env=pointmass", "explore=coherent-mc"])[0].cells()
    assert (
        variant.overrides[2:3] == ("explore=coherent",) and variant.overrides[-1] == "coherent.integration=mc"
    )


REFUSALS = {
    "a bad value in a cell": (["lr=abc"], "'lr'"),
    "an unknown key": (["lrr=0.1"], "unknown key 'lrr'"),
    "an unknown strategy": (
        ["explore=[action,nosuch]"],
        "unknown strategy 'nosuch' (allowed: action, coherent",
    ),
    "a refused pair": (["algo=[ppo,sac]", "explore=[action,noisynet]"], "algo=sac explore=noisynet"),
    "an unknown algorithm": (["algo=dqn"], "'dqn' (allowed: ppo, a2c, sac)"),
    "a claim on no strategy": (["compare=[coherent>nosuch]"], "'nosuch' (allowed: action, coherent)"),
    "an unknown metric": (["metrics=[final,speed]"], "'speed' (allowed: final, auc, reach)"),
    "a key given twice": (["seeds=2", "seeds=3"], "duplicated key 'seeds'"),
    "a bad number of seeds": (["seeds=0"], "'seeds': 0 (allowed: an integer >= 1)"),
    "a bad command key": (["workers=-1"], "'workers'"),
    "a cell that is not selected": (["cells=[nosuch/*]"], "unknown cell 'nosuch/*'"),
}


@pytest.mark.parametrize("case", sorted(REFUSALS))
def test_bad_input_is_refused_in_one_line_before_anything_is_written(tmp_path, monkeypatch, capsys, case):
    monkeypatch.chdir(tmp_path)
    items, said = REFUSALS[case]
    explore = [] if any(i.startswith("explore=") for i in items) else ["explore=[action,coherent]"]
    assert command.main(["env=pointmass", *explore, "out=s", *TINY, *items]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and said in err, err
    assert "allowed" in err or "unknown key" in err or "duplicated" in err
    assert _tree(tmp_path) == []


def test_a_bad_study_file_and_a_folder_of_another_study_are_refused(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    cases = {
        "tasks: [pointmass\n": "not valid YAML at line",
        "- a list\n": "list (allowed: a YAML mapping)",
        "tasks: [pointmass]\nalgos: [ppo]\nstrategies: [action]\ncolour: red\n": "unknown key 'colour'",
        "tasks: [pointmass]\nalgos: [ppo]\n": "missing key 'strategies'",
        "tasks: [pointmass]\nalgos: [ppo]\nstrategies: {a: {explore: nosuch}}\n": "unknown strategy 'nosuch'",
    }
    for text, said in cases.items():
        (tmp_path / "s.yaml").write_text(text)
        assert command.main(["s.yaml"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and said in err, (text, err)
    assert (
        command.main(["nosuch.yaml"]) == 2 and "invalid study file 'nosuch.yaml'" in capsys.readouterr().err
    )
    # A folder that holds another study, or files of none: refused, left as it was.
    other = tmp_path / "taken"
    other.mkdir()
    (other / "study.json").write_text(json.dumps({"name": "other"}))
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    (mixed / "notes.txt").write_text("mine")
    before = _tree(tmp_path)
    for out, said in ((other, "holds study 'other'"), (mixed, "holds 'notes.txt', no part of study")):
        assert command.main(["env=pointmass", "explore=action", f"out={out}", "name=mine"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and said in err and "allowed" in err, err
    assert _tree(tmp_path) == before


def test_the_command_starts_and_refuses_without_jax(tmp_path):
    code = (
        "import sys\n"
        "from coherent_jax.study.command import main\n"
        "assert main(['--help']) == 0\n"
        "assert main(['env=pointmass', 'explore=nosuch']) == 2\n"
        f"assert main(['env=pointmass', 'explore=action', 'status=true', 'out={tmp_path / 's'}']) == 0\n"
        "heavy = ('jax', 'flax', 'optax', 'mujoco', 'numpy', 'matplotlib')\n"
        "heavy = sorted(m for m in heavy if m in sys.modules)\n"
        "assert not heavy, heavy\n"
        "print('ok')\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], env=child_env(), capture_output=True, text=True, cwd=tmp_path
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().endswith("ok") and not (tmp_path / "s").exists()


# ------------------------------------------------------------------ running cells (stand-in sweeps)
def _stand_in(monkeypatch, fail: str = "", seconds: float = 0.0):
    """Each cell's sweep replaced by a short process that writes what a finished sweep writes
    (one point's config and metrics, sweep.json); `fail` names a cell whose sweep exits 1."""

    def sweep_command(cell: Cell, study_dir: Path) -> list[str]:
        sweep = cell_dir(cell, study_dir) / "sweep"
        code = (
            "import json, pathlib, sys, time\n"
            f"time.sleep({seconds})\n"
            f"if {cell.name == fail}: sys.exit(1)\n"
            f"p = pathlib.Path({str(sweep)!r}) / 'p000-seed=0'\n"
            "p.mkdir(parents=True, exist_ok=True)\n"
            "(p / 'config.yaml').write_text('seed: 0\\n')\n"
            "row = {'env_steps': 32, 'eval/episode_return': 1.5}\n"
            "(p / 'metrics.jsonl').write_text(json.dumps(row) + '\\n')\n"
            "(p.parent / 'sweep.json').write_text(json.dumps({'sweep_env_steps_per_s': 100.0}))\n"
        )
        return [sys.executable, "-c", code]

    monkeypatch.setattr(study_cell, "sweep_command", sweep_command)


def test_a_study_runs_every_cell_with_its_workers_and_continues_where_it_stopped(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    items = ["env=pointmass", "explore=[action,coherent,pink]", "out=s", "workers=2", *TINY]
    _stand_in(monkeypatch, fail="pointmass/ppo/coherent")
    assert command.main(items) == 1
    out = capsys.readouterr()
    assert "failed: pointmass/ppo/coherent" in out.err
    assert (
        "[study] pointmass/ppo/action: done" in out.out and "2 done, 0 running, 0 left, 1 failed" in out.out
    )
    record = json.loads((tmp_path / "s" / "study.json").read_text())
    assert record["name"] == "s" and len(record["cells"]) == 3 and record["compare"][0] == "coherent > action"
    assert curves.tabled_cells(tmp_path / "s") == {"pointmass/ppo/action", "pointmass/ppo/pink"}
    # The same command again: the failed cell only, the others kept as they are.
    done = {p: p.stat().st_mtime_ns for p in (tmp_path / "s").glob("pointmass/ppo/[ap]*/sweep/sweep.json")}
    _stand_in(monkeypatch)
    assert command.main(items) == 0
    out = capsys.readouterr().out
    assert "pointmass/ppo/coherent: started" in out and "pointmass/ppo/action: started" not in out
    assert {p: p.stat().st_mtime_ns for p in done} == done
    study, _, _ = command.parse(items)
    assert all(cell_state(c, study.out) == "done" for c in study.cells())
    # The curves table rebuilt from the logs is the one the cells wrote as they finished.
    table = (tmp_path / "s" / curves.TABLE).read_bytes()
    assert command.main(["curves", "s"]) == 0 and (tmp_path / "s" / curves.TABLE).read_bytes() == table
    assert command.main(["curves", "nowhere"]) == 2 and "'nowhere'" in capsys.readouterr().err
    # Another specification of a cell in the same folder is refused, naming the cell.
    assert command.main([*items, "seeds=3"]) == 2
    assert "holds cell 'pointmass/ppo/action' of another specification" in capsys.readouterr().err


def test_a_killed_studys_sweeps_end_with_it(tmp_path):
    """SIGKILL of the study's process: its running sweeps get SIGTERM (they checkpoint and stop),
    so that the same command can continue the study at once."""
    code = (
        "import sys\n"
        "from coherent_jax.study import cell, command\n"
        "cell.sweep_command = lambda c, d: [sys.executable, '-c', 'import time; time.sleep(300)']\n"
        f"command.main(['env=pointmass', 'explore=[action,pink]', 'workers=2', 'out={tmp_path / 's'}'])\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], env=child_env(), cwd=tmp_path, stdout=subprocess.DEVNULL
    )
    pids = tmp_path / "s" / "pointmass" / "ppo"
    deadline = time.monotonic() + 120
    while len(list(pids.glob("*/running.pid"))) < 2:
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.2)
    sweeps = [int(p.read_text()) for p in pids.glob("*/running.pid")]
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    deadline = time.monotonic() + 30
    while any(study_cell._pid_alive(pid) for pid in sweeps):
        assert time.monotonic() < deadline, "a sweep outlived its study"
        time.sleep(0.2)


def test_one_study_process_at_a_time(tmp_path, monkeypatch):
    with execute.holding(tmp_path / "s"):
        code = (
            "from coherent_jax.study import execute\n"
            f"with execute.holding(__import__('pathlib').Path({str(tmp_path / 's')!r})):\n    pass\n"
        )
        out = subprocess.run([sys.executable, "-c", code], env=child_env(), capture_output=True, text=True)
        assert "is in use by process" in out.stderr and f"{os.getpid()}" in out.stderr
    assert (tmp_path / "s" / "study.lock").exists()


def test_the_default_workers_fit_the_cores_and_the_memory():
    cores = len(os.sched_getaffinity(0))
    assert 1 <= execute.default_workers() <= cores


def test_the_executor_interface_is_what_the_loop_uses(tmp_path, monkeypatch):
    """Another executor (a cluster's) plugs in by `slots`, `start`, `wait` and `stop`."""

    class Inline:
        slots = 1

        def __init__(self):
            self.ended = []

        def start(self, job):
            self.ended.append((job, subprocess.call(job.command, cwd=job.cwd)))

        def wait(self, timeout):
            ended, self.ended = self.ended, []
            return ended

        def stop(self):
            pass

    _stand_in(monkeypatch)
    study, _, _ = command.parse(["env=pointmass", "explore=[action,pink]", f"out={tmp_path / 's'}"])
    (tmp_path / "s").mkdir()
    failed = execute.run_cells(study.cells(), study.out, tmp_path, Inline(), stream=open(os.devnull, "w"))
    assert failed == [] and all(cell_state(c, study.out) == "done" for c in study.cells())


def test_the_study_imports_no_benchmark():
    """A study runs sweeps; the benchmarks (``benchmarks/``) are no part of it."""
    for path in sorted((ROOT / "coherent_jax" / "study").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom):
                names = [node.module or "", *(f"{node.module}.{a.name}" for a in node.names)]
            assert not any(n.startswith(("coherent_jax.bench", "benchmarks")) for n in names), path


def test_spec_refuses_two_tasks_of_one_name():
    with pytest.raises(StudyError, match="two tasks are named 'Good'"):
        spec.make_study(
            {"tasks": ["a.py:Good", "b.py:Good"], "algos": ["ppo"], "strategies": ["action"]}, ROOT, "x"
        )


# ------------------------------------------------------------------ slow: real sweeps
@pytest.mark.slow
def test_a_plan_probes_each_distinct_program_once_and_writes_nothing_but_its_cache(tmp_path, monkeypatch):
    """Two cells that differ only in a sweepable value (lr) compile one program: one probe."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "s.yaml").write_text(
        "tasks: [pointmass]\nalgos: [ppo]\nseeds: 1\ntotal_steps: 64\n"
        "strategies: {a: {explore: action}, b: {explore: action, settings: [lr=0.001]}}\n"
        "settings:\n" + "".join(f"  - '{item}'\n" for item in TINY)
    )
    env = {**child_env(), "XDG_CACHE_HOME": str(tmp_path / "cache")}
    before = _tree(tmp_path)
    out = subprocess.run(
        [sys.executable, "-m", "coherent_jax.study", "s.yaml", "plan=true", "probe=1"],
        env=env, capture_output=True, text=True, cwd=tmp_path, timeout=900,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    assert "2 cells, 1 distinct programs" in out.stdout and out.stdout.count("probing program") == 1
    assert "CPU hours" in out.stdout
    after = [p for p in _tree(tmp_path) if not p.startswith("cache")]
    assert after == before and (tmp_path / "cache" / "coherent_jax" / "study-probes.json").is_file()


def _metrics(study_dir: Path) -> dict[str, list[dict]]:
    """Every point's metrics rows without their times (what differs between two runs)."""
    found = {}
    for path in sorted(study_dir.glob("**/metrics.jsonl")):
        rows = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
        found[path.relative_to(study_dir).as_posix()] = [
            {k: v for k, v in r.items() if not k.endswith("_s") and "per_s" not in k and k != "time_s"}
            for r in rows
        ]
    return found


@pytest.mark.slow
def test_a_killed_study_continues_to_the_results_of_an_uninterrupted_one(tmp_path):
    """SIGKILL of the study's process mid-way (its sweeps end with it, checkpointed), then the
    same command: no finished cell is recomputed, and the curves and metrics are those of a study
    that ran through. Then `verify` on the finished study tells a code change from a CPU change."""
    items = ["env=pointmass", "explore=[action,pink]", "seeds=2", "total_steps=512", "checkpoint_every=1",
             "workers=1", "name=kill", *TINY]  # fmt: skip
    run = [sys.executable, "-m", "coherent_jax.study", *items]
    env = child_env()
    whole = subprocess.run(
        [*run, f"out={tmp_path / 'whole'}"], env=env, capture_output=True, text=True, cwd=tmp_path
    )
    assert whole.returncode == 0, whole.stderr[-2000:]
    killed = tmp_path / "killed"
    proc = subprocess.Popen([*run, f"out={killed}"], env=env, cwd=tmp_path, stdout=subprocess.DEVNULL)
    logs = killed / "pointmass" / "ppo" / "pink" / "sweep"
    deadline = time.monotonic() + 900
    while not any('"iteration": 4' in p.read_text() for p in logs.glob("*/metrics.jsonl")):
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.5)
    first = (killed / "pointmass" / "ppo" / "action" / "sweep" / "sweep.json").stat().st_mtime_ns
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    again = subprocess.run([*run, f"out={killed}"], env=env, capture_output=True, text=True, cwd=tmp_path)
    assert again.returncode == 0, again.stderr[-2000:]
    assert "pointmass/ppo/action: started" not in again.stdout
    assert (killed / "pointmass" / "ppo" / "action" / "sweep" / "sweep.json").stat().st_mtime_ns == first
    assert (killed / curves.TABLE).read_bytes() == (tmp_path / "whole" / curves.TABLE).read_bytes()
    assert _metrics(killed) == _metrics(tmp_path / "whole")
    _verify_tells_a_code_change_from_a_cpu_change(run, tmp_path / "whole", env, tmp_path)


def _verify_tells_a_code_change_from_a_cpu_change(run, study, env, cwd):
    """``verify=true`` on a finished cell: bit-identical (exit 0); with one logged value moved
    by one ulp, as a changed rounding would move it, "differs ... on the same CPU" (exit 1);
    with that and the cell's CPU recorded as another family, "not comparable" (exit 0)."""
    name = "pointmass/ppo/action"
    argv = [*run, f"out={study}", "verify=true", f"cells=[{name}]", "iterations=2"]

    def verify():
        done = subprocess.run(argv, env=env, capture_output=True, text=True, cwd=cwd, timeout=900)
        line = next((x for x in done.stdout.splitlines() if x.startswith(f"kill/{name}:")), done.stderr)
        return done.returncode, line

    status, line = verify()
    assert status == 0 and "bit-identical" in line, line
    table = curves.table_path(study)
    rows = curves.read_table(table)
    i = next(i for i, r in enumerate(rows) if r[0] == name and r[3] is not None)
    rows[i] = (*rows[i][:3], float(np.nextafter(np.float32(rows[i][3]), np.float32(np.inf))), *rows[i][4:])
    curves.write_table(table, rows)
    status, line = verify()
    assert status == 1 and "differs from iteration 2 (the first compared) on the same CPU (" in line, line
    assert "last 'Changes bits:' commit: " in line, line
    versions = study / name / "sweep" / "versions.json"
    recorded = json.loads(versions.read_text())
    versions.write_text(json.dumps({**recorded, "cpu_family": recorded["cpu_family"] + 1}))
    status, line = verify()
    assert status == 0 and f"not comparable: made on CPU {recorded['cpu_model']} (" in line, line
    assert (
        f"family {recorded['cpu_family'] + 1} model" in line
        and f"family {recorded['cpu_family']} model" in line
    )
