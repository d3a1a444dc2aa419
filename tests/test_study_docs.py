"""docs/study.md, as written: its env file and study file, then every ``python -m
coherent_jax.study`` command it shows, in order, in a fresh folder. A user's
`gymnasium.Env` and a built-in task with three strategies, from the plan (which writes
nothing but its cache) to the report; the same study from the command line finds its
cells done. Real sweeps: slow."""

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import child_env

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "study.md"


def doc_files(text: str) -> dict[str, str]:
    """The fenced blocks whose first line is ``# FILE``: file name -> content."""
    found = {}
    for body in re.findall(r"```(?:python|yaml)\n(.*?)```", text, flags=re.S):
        first = body.splitlines()[0]
        if first.startswith("# ") and "." in first:
            found[first[2:].strip()] = body
    return found


def doc_commands(text: str) -> list[str]:
    """Every indented ``python -m coherent_jax.study`` command, in order."""
    return [line.strip() for line in text.splitlines() if line.startswith("    python -m coherent_jax.study")]


def test_the_doc_shows_its_files_and_commands():
    text = DOC.read_text()
    assert set(doc_files(text)) == {"target_line.py", "study.yaml"}
    commands = doc_commands(text)
    assert commands[0].endswith("plan=true probe=1") and commands[-1].endswith("report target-study")
    assert any("env=[target_line.py:TargetLine,pointmass]" in c for c in commands)


@pytest.mark.slow
def test_every_command_of_the_doc_runs_as_written(tmp_path):
    text = DOC.read_text()
    for name, body in doc_files(text).items():
        (tmp_path / name).write_text(body)
    env = {**child_env(), "XDG_CACHE_HOME": str(tmp_path / "cache")}
    outputs = []
    for command in doc_commands(text):
        before = sorted(p.name for p in tmp_path.iterdir())
        argv = [sys.executable, *shlex.split(command)[1:]]
        done = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=3600)
        assert done.returncode == 0, (command, done.stderr[-3000:])
        outputs.append(done.stdout)
        if "plan=true" in command:  # nothing written but the cache
            assert sorted(p.name for p in tmp_path.iterdir()) == sorted({*before, "cache"})
            assert "6 cells, 6 distinct programs" in done.stdout and "CPU hours" in done.stdout
    study = tmp_path / "target-study"
    cli = next(
        out
        for c, out in zip(doc_commands(text), outputs, strict=True)
        if c.startswith("python -m coherent_jax.study env=")
    )
    assert "started" not in cli and "6 cells" in cli  # the file's cells, found done
    report = (study / "REPORT.md").read_text()
    assert "| TargetLine/ppo/coherent | 3 |" in report and "| pointmass/ppo/pink | 3 |" in report
    assert "## Verdicts" in report and "coherent improves on pink" in report
    for figure in ("curves-ppo.png", "profile-ppo.png", "improvement.png"):
        assert (study / "figures" / figure).stat().st_size > 1000
