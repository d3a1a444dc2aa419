"""``executor=ray``: its refusals (no Ray installed, a bad executor or address: one line, exit
status 2, nothing written), a cell running on another machine seen by its folder's lock, and,
marked slow, a study on a Ray head of its own on loopback whose worker is killed mid-cell: the
study finishes, the killed cell resumes from its checkpoint, and every cell's metrics are those
of the same study on the local executor.
"""

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from helpers import child_env

from coherent_jax.run import rundir
from coherent_jax.study import command, curves
from coherent_jax.study.cell import PID_FILE, Cell, cell_dir, cell_state, running_pid

TINY = (
    "num_envs=4", "unroll_length=8", "num_minibatches=2", "episode_length=32", "eval_episodes=2",
    "eval_every=2", "policy_hidden=[16,16]", "value_hidden=[16,16]", "progress=false", "tensorboard=false",
)  # fmt: skip
# Ray on this machine only: with its cluster mode off, every address it uses is on loopback
# (else it resolves 127.0.0.1 to the machine's network address); no usage reports; no token
# authentication, for the head and the study alike (a head would turn it on when a token is in
# ~/.ray, and a study given the head's address would not).
LOOPBACK = {
    "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
    "RAY_USAGE_STATS_ENABLED": "0",
    "RAY_AUTH_MODE": "disabled",
}


def _tree(path: Path) -> list[str]:
    return sorted(p.relative_to(path).as_posix() for p in path.rglob("*"))


@pytest.mark.parametrize(
    "items, said",
    [
        (["executor=slurm"], "invalid value for 'executor': 'slurm' (allowed: local, ray)"),
        (["executor=ray", "ray.address=head"], "invalid value for 'ray.address': 'head' (allowed: auto"),
        (["executor=ray", "ray.cpus_per_cell=0"], "invalid value for 'ray.cpus_per_cell': '0'"),
        (["executor=ray"], 'needs the ray package, which is not installed (allowed: local; or install it: '
                           'pip install -e ".[ray]")'),
    ],
    ids=["bad executor", "bad address", "bad cpus_per_cell", "no ray"],
)  # fmt: skip
def test_a_bad_executor_and_executor_ray_without_ray_are_refused(tmp_path, monkeypatch, capsys, items, said):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails, as where it is not installed
    assert command.main(["env=pointmass", "explore=[action,pink]", "out=s", *TINY, *items]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and said in err, err
    assert _tree(tmp_path) == []


def test_a_sweep_on_another_machine_runs_while_it_holds_its_folders_lock(tmp_path):
    """``running.pid`` written by a cluster's node names it: a pid of another machine cannot be
    looked up here, so the sweep's folder lock (on the shared filesystem) says whether it runs."""
    cell = Cell("s", "pointmass/ppo/action", ("env=pointmass",), 1)
    d = cell_dir(cell, tmp_path)
    (d / "sweep").mkdir(parents=True)
    (d / PID_FILE).write_text(f"{os.getpid()} elsewhere.example\n")
    assert running_pid(cell, tmp_path) is None and cell_state(cell, tmp_path) == "stopped"
    with rundir.acquire(d / "sweep", "run_dir"):
        assert running_pid(cell, tmp_path) == os.getpid() and cell_state(cell, tmp_path) == "running"
    (d / PID_FILE).write_text(f"{os.getpid()} {socket.gethostname()}\n")  # this machine: by its pid
    assert running_pid(cell, tmp_path) == os.getpid()


# ------------------------------------------------------------------ slow: a Ray head of its own
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stat(pid: int) -> list[str]:
    """The fields of /proc/PID/stat after the command's name: state, ppid, pgrp, session, ..."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def _session(sid: int) -> list[int]:
    """The live processes of session `sid` (the head's: it and every Ray process it starts)."""
    found = []
    for d in Path("/proc").iterdir():
        try:
            fields = _stat(int(d.name)) if d.name.isdigit() else []
            if fields and int(fields[3]) == sid and fields[0] != "Z":  # a zombie is ended
                found.append(int(d.name))
        except (OSError, IndexError, ValueError):
            continue
    return found


class Head:
    """A Ray head on loopback (``ray start --head --block`` in a session of its own)."""

    def __init__(self, root: Path) -> None:
        self.root, port = root, _free_port()
        self.address, self.env = f"127.0.0.1:{port}", {**child_env(), **LOOPBACK}
        self.log = root / "head.log"
        command = [
            sys.executable, "-m", "ray.scripts.scripts", "start", "--head", "--node-ip-address=127.0.0.1",
            f"--port={port}", "--num-cpus=2", "--include-dashboard=false", f"--dashboard-port={_free_port()}",
            f"--dashboard-agent-listen-port={_free_port()}", "--disable-usage-stats", f"--temp-dir={root}",
            "--object-store-memory=80000000", "--block",
        ]  # fmt: skip
        with open(self.log, "w") as log:
            self.proc = subprocess.Popen(
                command, env=self.env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )

    def wait_ready(self, timeout: float = 180.0) -> None:
        deadline = time.monotonic() + timeout
        while "Ray runtime started" not in self.log.read_text():
            assert self.proc.poll() is None, self.log.read_text()[-2000:]
            assert time.monotonic() < deadline, "the Ray head did not start"
            time.sleep(0.5)

    def stop(self) -> None:
        """Ends every process of the head's session (SIGKILL: a test's cluster keeps nothing)."""
        deadline = time.monotonic() + 30
        while (left := _session(self.proc.pid)) and time.monotonic() < deadline:
            for pid in left:
                with contextlib.suppress(ProcessLookupError):  # ended in between
                    os.kill(pid, signal.SIGKILL)
            time.sleep(0.2)
            self.proc.poll()
        self.proc.wait(timeout=30)


@pytest.fixture
def ray_head():
    """A Ray head of two CPUs, stopped at the end whatever happens. Its folder is short (Ray's
    socket paths must fit in 107 bytes)."""
    root = Path(tempfile.mkdtemp(prefix="ray", dir="/tmp"))
    head = Head(root)
    try:
        yield head
    finally:
        head.stop()
        shutil.rmtree(root, ignore_errors=True)


def _metrics(study_dir: Path) -> dict[str, list[dict]]:
    """Every point's metrics rows without their times (what differs between two runs)."""
    found = {}
    for path in sorted(study_dir.glob("**/metrics.jsonl")):
        rows = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
        found[path.relative_to(study_dir).as_posix()] = [
            {k: v for k, v in r.items() if not k.endswith("_s") and "per_s" not in k} for r in rows
        ]
    return found


def _iterations(sweep: Path) -> int:
    """The last iteration the cell's points have all logged."""
    logs = [p.read_text().splitlines() for p in sweep.glob("*/metrics.jsonl")]
    return min((len([x for x in rows if x.endswith("}")]) for rows in logs), default=0) if logs else 0


@pytest.mark.slow
def test_a_study_on_ray_survives_a_killed_worker_to_the_local_executors_results(tmp_path, ray_head):
    """The sweep of a cell and its Ray worker SIGKILLed mid-cell (a node lost): the executor starts
    the cell again, its sweep resumes from its checkpoint (redoing at most the iterations after
    it), and the study's metrics and curves are those of the local executor's."""
    # Two cells of one program (they differ in lr only): the local study compiles it once (one
    # worker), and the study on Ray loads it from the test run's compilation cache.
    (tmp_path / "study.yaml").write_text(
        "name: ray\ntasks: [pointmass]\nalgos: [ppo]\nseeds: 2\ntotal_steps: 2048\n"
        "strategies: {a: {explore: action}, b: {explore: action, settings: [lr=0.001]}}\n"
        "settings:\n" + "".join(f"  - '{item}'\n" for item in (*TINY, "checkpoint_every=1"))
    )
    run = [sys.executable, "-m", "coherent_jax.study", "study.yaml"]
    started = time.monotonic()
    local = subprocess.run(
        [*run, f"out={tmp_path / 'local'}", "workers=1"],
        env=ray_head.env,
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert local.returncode == 0, local.stderr[-2000:]
    ray_head.wait_ready()
    local_s, started = time.monotonic() - started, time.monotonic()
    on_ray = tmp_path / "ray"
    proc = subprocess.Popen(
        [*run, f"out={on_ray}", "workers=2", "executor=ray", f"ray.address={ray_head.address}"],
        env=ray_head.env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    cell = on_ray / "pointmass" / "ppo" / "a"
    deadline = time.monotonic() + 600
    while _iterations(cell / "sweep") < 3 or not (cell / "running.pid").exists():
        assert time.monotonic() < deadline and proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    sweep, host = (cell / "running.pid").read_text().split()
    worker = int(_stat(int(sweep))[1])
    assert host == socket.gethostname() and b"ray" in Path(f"/proc/{worker}/cmdline").read_bytes()
    os.kill(worker, signal.SIGSTOP)  # it cannot see its sweep end; then both go at once
    os.kill(int(sweep), signal.SIGKILL)
    logged = _iterations(cell / "sweep")
    os.kill(worker, signal.SIGKILL)
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-2000:]
    assert "pointmass/ppo/a: its Ray task was lost (WorkerCrashedError" in out, out
    assert "restart 1 of 3, from its checkpoint" in out and "restart 2" not in out, out
    resumed = int((cell / "run.log").read_text().split("resuming after iteration ")[1].split()[0])
    print(f"local study {local_s:.0f} s, on Ray {time.monotonic() - started:.0f} s; killed after iteration "
          f"{logged}, resumed after iteration {resumed}")  # fmt: skip
    assert 0 <= logged - resumed <= 1 and logged < 64  # checkpoint_every=1: at most one redone
    assert _metrics(on_ray) == _metrics(tmp_path / "local") and len(_metrics(on_ray)) == 4
    assert (on_ray / curves.TABLE).read_bytes() == (tmp_path / "local" / curves.TABLE).read_bytes()
