"""`coherent_jax.study.carry` through experiments/reproduce.py: a stopped cell packed, carried
and resumed.

A cell's files are laid out as a sweep leaves them when stopped; no training runs.
"""

import os
import shutil
import sys

import numpy as np
import pytest
from cell_fakes import fake_sweep, reproduce
from helpers import commit_all

from coherent_jax.study import carry, cost, curves
from coherent_jax.study import cell as study_cell
from coherent_jax.study.cell import cell_dir, cell_state, progress, sweep_command


def _stopped_cell_with_a_checkpoint(cell, results):
    """A stopped cell as a SIGTERM leaves it: checkpoint, configs, logs, and what stays local."""
    d = fake_sweep(cell, results, finished=False)
    sweep = d / "sweep"
    (sweep / "checkpoint.msgpack").write_bytes(np.random.default_rng(0).bytes(4096))
    for name in ("config.yaml", "grid.json", "versions.json", "versions-resumed-7.json"):
        (sweep / name).write_text(f"{name}\n")
    (sweep / "run.lock").write_text("123\n")
    (sweep / "seed=0" / "tb").mkdir()
    (sweep / "seed=0" / "tb" / "events.out.tfevents.1").write_bytes(b"\0" * 64)
    (d / "run.log").write_text("progress bars\n")
    return d


def test_a_stopped_cell_is_carried_by_its_packed_state_and_unpacked_whole(tmp_path):
    stopped, finished = reproduce.select("protocol", ["hopper/a2c/action-thesis", "hopper/a2c/psne-thesis"])
    d = _stopped_cell_with_a_checkpoint(stopped, tmp_path)
    sweep = d / "sweep"
    kept = {
        "checkpoint.msgpack", "config.yaml", "grid.json", "versions.json", "versions-resumed-7.json",
        "seed=0/config.yaml", "seed=0/metrics.jsonl",
    }  # fmt: skip
    before = {f.relative_to(sweep).as_posix(): f.read_bytes() for f in sweep.rglob("*") if f.is_file()}
    path = carry.pack(d)
    first = path.read_bytes()
    assert carry.pack(d).read_bytes() == first  # the same files, the same bytes
    fraction = progress(stopped, tmp_path / stopped.suite)[0]
    shutil.rmtree(sweep)  # a clone elsewhere: the carry file, no sweep directory
    assert cell_state(stopped, tmp_path / stopped.suite) == "carried"
    assert progress(stopped, tmp_path / stopped.suite)[0] == fraction == pytest.approx(0.5 / 5)
    assert "carried" in cost.status([stopped], tmp_path / stopped.suite)
    assert carry.unpack(d) and not carry.unpack(d)  # once: the sweep directory is back
    after = {f.relative_to(sweep).as_posix(): f.read_bytes() for f in sweep.rglob("*") if f.is_file()}
    assert after == {k: v for k, v in before.items() if k in kept} and set(after) == kept
    assert cell_state(stopped, tmp_path / stopped.suite) == "stopped"
    assert any(a.startswith("resume=") for a in sweep_command(stopped, tmp_path / stopped.suite))
    # Refused, leaving the carry file as it was: a pack over the limit, a finished cell.
    with pytest.raises(carry.CarryError, match=r"packs to .* MB \(allowed: at most"):
        carry.pack(d, max_bytes=3000)  # 4.2 kB of files, 4.6 kB packed
    assert path.read_bytes() == first
    e = fake_sweep(finished, tmp_path, finished=True)
    with pytest.raises(carry.CarryError, match="has finished"):
        carry.pack(e)
    assert not carry.carry_path(e).exists()
    # A finished cell drops its carry file (untracked here: nothing to commit).
    assert carry.drop(d, tmp_path) == [] and not path.exists()


def test_a_tracked_carry_file_is_removed_in_the_commit_also_when_the_finish_deleted_it(tmp_path):
    """A cell that finishes in a run without --commit deletes its carry file at once; the
    later commit must still commit that removal."""
    import subprocess

    repo = tmp_path / "repo"
    cells = {}
    for name in ("finished-here", "finished-before"):
        d = repo / "results" / name
        d.mkdir(parents=True)
        carry.carry_path(d).write_bytes(b"packed state")
        cells[name] = d
    git = commit_all(repo, "carried")
    carry.carry_path(cells["finished-before"]).unlink()  # the run without --commit
    for d in cells.values():
        assert carry.drop(d, repo) == [str(carry.carry_path(d))]
        assert not carry.carry_path(d).exists()
    assert carry.drop(cells["finished-here"], repo) == [str(carry.carry_path(cells["finished-here"]))]
    paths = [str(carry.carry_path(d)) for d in cells.values()]
    subprocess.run(git + ["add", "--", *paths], check=True, capture_output=True)
    subprocess.run(git + ["commit", "-q", "-m", "finished", "--", *paths], check=True, capture_output=True)
    listed = subprocess.run(git + ["ls-files"], check=True, capture_output=True, text=True).stdout
    status = subprocess.run(git + ["status", "--porcelain"], check=True, capture_output=True, text=True)
    assert listed == "" and status.stdout == ""


def test_a_carry_file_reaching_outside_its_sweep_is_refused_and_nothing_is_written(tmp_path):
    import io
    import tarfile

    (cell,) = reproduce.select("protocol", ["hopper/a2c/action-thesis"])
    d = cell_dir(cell, tmp_path / cell.suite)
    d.mkdir(parents=True)
    with tarfile.open(carry.carry_path(d), "w:gz") as tar:
        for name in ("sweep/config.yaml", "sweep/../../escaped.txt"):
            info = tarfile.TarInfo(name)
            info.size = 3
            tar.addfile(info, io.BytesIO(b"abc"))
    with pytest.raises(carry.CarryError, match=r"member 'sweep/\.\./\.\./escaped.txt' \(allowed"):
        carry.unpack(d)
    assert sorted(p.name for p in d.iterdir()) == [carry.CARRY]
    assert not (tmp_path / "protocol" / "hopper" / "escaped.txt").exists()


def test_pack_refuses_a_running_cell_and_packs_none(tmp_path, capsys):
    stopped, running = reproduce.select("protocol", ["hopper/a2c/action-thesis", "hopper/a2c/psne-thesis"])
    a = _stopped_cell_with_a_checkpoint(stopped, tmp_path)
    b = _stopped_cell_with_a_checkpoint(running, tmp_path)
    (b / "running.pid").write_text(f"{os.getpid()}\n")
    args = ["protocol", "--cells", "hopper/a2c/*", "--results", str(tmp_path), "--pack"]
    assert reproduce.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'hopper/a2c/psne-thesis' is running" in err[0]
    assert not (a / "carry.tar.gz").exists() and not (b / "carry.tar.gz").exists()
    (b / "running.pid").unlink()
    assert reproduce.main(args) == 0
    assert (a / "carry.tar.gz").exists() and (b / "carry.tar.gz").exists()
    # A cell too large to carry (as an SAC checkpoint with its replay buffer) is named and
    # passed over, before its archive is built; the others are packed.
    (b / "carry.tar.gz").unlink()
    big = b / "sweep" / "checkpoint.msgpack"
    with open(big, "r+b") as f:
        f.truncate(2 * carry.MAX_BYTES + 1)
    (a / "carry.tar.gz").unlink()
    assert reproduce.main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "psne-thesis' holds 32 MB to pack (allowed: at most 16 MB" in err[0], err
    assert (a / "carry.tar.gz").exists() and not (b / "carry.tar.gz").exists()


def test_a_carried_cell_is_unpacked_before_its_sweep_resumes_and_its_carry_file_goes(tmp_path, monkeypatch):
    (cell,) = reproduce.select("protocol", ["hopper/a2c/action-thesis"])
    d = _stopped_cell_with_a_checkpoint(cell, tmp_path)
    carry.pack(d)
    shutil.rmtree(d / "sweep")
    seen = []

    def finishing_sweep(c, study_dir):  # stands for `resume=`: records what it found, then finishes
        sweep = cell_dir(c, study_dir) / "sweep"
        seen.append(sorted(p.name for p in sweep.iterdir()))
        code = f"import pathlib; pathlib.Path({str(sweep / 'sweep.json')!r}).write_text('{{}}')"
        return [sys.executable, "-c", code]

    monkeypatch.setattr(study_cell, "sweep_command", finishing_sweep)
    monkeypatch.setattr(curves, "update_table", lambda *a: None)
    assert reproduce.main(["protocol", "--cells", cell.name, "--results", str(tmp_path)]) == 0
    assert seen and "checkpoint.msgpack" in seen[0] and "seed=0" in seen[0]
    assert cell_state(cell, tmp_path / cell.suite) == "done" and not carry.carry_path(d).exists()
