"""Several processes through `jax.distributed` on one machine (loopback only, every wait bounded).

Each process is a real ``python -m coherent_jax.train ... distributed=true`` with the
environment variables of docs/runs.md, one CPU device each; the reference is one process
with two host devices (``--xla_force_host_platform_device_count=2``): the same mesh
of two devices, so the same program, and the two must agree metric for metric.
"""

import json
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from flax import serialization
from helpers import child_env

ROOT = Path(__file__).resolve().parents[1]
ITERATIONS = 60
CHECKPOINT_EVERY = 10
TINY = [
    "env=pointmass",
    "num_envs=8",
    "unroll_length=8",
    "ppo.num_minibatches=2",
    "eval_episodes=2",
    "episode_length=50",
    "eval_every=5",
    "progress=false",
    "tensorboard=false",
    f"total_steps={ITERATIONS * 64}",
    f"checkpoint_every={CHECKPOINT_EVERY}",
]
# Failure detection bounds of the tests (seconds); the library's defaults are longer.
HEARTBEAT_S = 10
INIT_S = 3
WAIT_S = 900  # upper bound on any one launch (compiles on a loaded 2-core machine)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(args, out: Path, process_id=None, num_processes=2, port=None, devices=1, extra_env=None):
    """Starts ``python -m coherent_jax.train args`` (one process of a run when `process_id` is given)."""
    env = child_env()
    for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"):
        env.pop(name, None)
    env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    env["COHERENT_JAX_HEARTBEAT_TIMEOUT"] = str(HEARTBEAT_S)
    if process_id is not None:
        env["JAX_COORDINATOR_ADDRESS"] = f"127.0.0.1:{port}"
        env["JAX_NUM_PROCESSES"] = str(num_processes)
        env["JAX_PROCESS_ID"] = str(process_id)
    env.update(extra_env or {})
    return subprocess.Popen(
        [sys.executable, "-m", "coherent_jax.train", *args],
        stdout=open(out.with_suffix(".out"), "w"),
        stderr=open(out.with_suffix(".err"), "w"),
        env=env,
        cwd=ROOT,
    )


def finish(procs, timeout=WAIT_S) -> list[int]:
    """Exit statuses of `procs`, waiting at most `timeout` seconds in all."""
    deadline = time.monotonic() + timeout
    return [p.wait(timeout=max(deadline - time.monotonic(), 0.1)) for p in procs]


def kill_all(procs) -> None:
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=30)


def wait_for_rows(path: Path, rows: int, procs, timeout=WAIT_S) -> None:
    """Waits until ``metrics.jsonl`` has `rows` lines; fails if a process ends first."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.is_file() and len(path.read_text().splitlines()) >= rows:
            return
        ended = [p.returncode for p in procs if p.poll() is not None]
        assert not ended, f"a process ended before row {rows}: {ended}"
        time.sleep(0.02)
    raise AssertionError(f"no row {rows} in {path} within {timeout} s")


def rows(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines()]


def text(path: Path, suffix: str) -> str:
    return path.with_suffix(suffix).read_text()


def assert_same_rows(got: list[dict], want: list[dict]) -> None:
    assert [r["iteration"] for r in got] == list(range(1, ITERATIONS + 1))
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        assert a.keys() == b.keys()
        for k in b:
            if k == "time_s":
                continue
            if b[k] is None:
                assert a[k] is None, (a["iteration"], k)
            else:
                assert a[k] == pytest.approx(b[k], rel=1e-5, abs=1e-6), (a["iteration"], k)


@pytest.mark.slow
def test_two_processes_match_two_devices_survive_sigkill_and_resume(tmp_path):
    """2 processes x 1 device == 1 process x 2 devices, through a SIGKILL of the coordinator and resumes.

    The 2-process run loses process 0 (the coordinator and writer) to SIGKILL after
    its first checkpoint: process 1 must stop by itself with one error line and
    status 4. The run is resumed once by a single process with two devices (another
    process count), killed again, and finished by the original two processes: every
    row and the final parameters equal the uninterrupted reference.
    """
    procs = []
    try:
        ref = start([*TINY, f"run_dir={tmp_path / 'ref'}"], tmp_path / "ref", devices=2)
        procs.append(ref)
        assert finish([ref]) == [0], text(tmp_path / "ref", ".err")[-3000:]

        run = tmp_path / "run"
        port = free_port()
        pair = [
            start([*TINY, "distributed=true", f"run_dir={run}"], tmp_path / f"a{i}", i, 2, port)
            for i in (0, 1)
        ]
        procs += pair
        wait_for_rows(run / "metrics.jsonl", CHECKPOINT_EVERY + 1, pair)
        pair[0].send_signal(signal.SIGKILL)
        killed_at = time.monotonic()
        status = finish([pair[1]], timeout=HEARTBEAT_S + 60)
        stopped_after = time.monotonic() - killed_at
        err = text(tmp_path / "a1", ".err")
        assert status == [4], err[-3000:]
        assert stopped_after < HEARTBEAT_S + 20, stopped_after
        errors = [ln for ln in err.splitlines() if "error" in ln.lower()]
        assert len(errors) == 1 and errors[0].startswith("error: process 1 of 2: "), err[-3000:]
        assert "stack trace" not in err and "Terminating process" not in err, err[-3000:]
        assert (run / "checkpoint.msgpack").is_file() and not (run / "summary.json").exists()

        # Another process count: one process with both devices continues the run.
        solo = start([f"resume={run}"], tmp_path / "b0", 0, 1, free_port(), devices=2)
        procs.append(solo)
        wait_for_rows(run / "metrics.jsonl", 2 * CHECKPOINT_EVERY + 1, [solo])
        solo.send_signal(signal.SIGKILL)
        finish([solo], timeout=60)

        port = free_port()
        pair = [start([f"resume={run}"], tmp_path / f"c{i}", i, 2, port) for i in (0, 1)]
        procs += pair
        assert finish(pair) == [0, 0], text(tmp_path / "c1", ".err")[-3000:]
        out0, out1 = text(tmp_path / "c0", ".out"), text(tmp_path / "c1", ".out")
        assert "resuming after iteration" in out0 and "resuming after iteration" in out1
    finally:
        kill_all(procs)

    # Only process 0 wrote: one row per iteration, not two.
    assert_same_rows(rows(run / "metrics.jsonl"), rows(tmp_path / "ref" / "metrics.jsonl"))
    got = serialization.msgpack_restore((run / "params.msgpack").read_bytes())
    want = serialization.msgpack_restore((tmp_path / "ref" / "params.msgpack").read_bytes())
    for a, b in zip(_leaves(got), _leaves(want), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    # Both processes end with the same parameters: the same final evaluation.
    done = [ln.split(",")[0] for ln in (out0 + out1).splitlines() if "done: eval return" in ln]
    assert len(done) == 2 and done[0] == done[1], done


def _leaves(tree) -> list[np.ndarray]:
    if isinstance(tree, dict):
        return [x for k in sorted(tree) for x in _leaves(tree[k])]
    return [np.asarray(tree)]


@pytest.mark.slow
def test_unreachable_coordinator_and_missing_peer_stop_in_one_line(tmp_path):
    """Without its coordinator (or its peer) a process stops after the join timeout: one line, status 4."""
    env = {"COHERENT_JAX_INIT_TIMEOUT": str(INIT_S)}
    procs = []
    try:
        t0 = time.monotonic()
        # Process 1 with nobody at the coordinator's port; process 0 of another run whose peer never comes.
        alone = [
            start(
                [*TINY, "distributed=true", f"run_dir={tmp_path / f'r{i}'}"],
                tmp_path / f"p{i}",
                i,
                2,
                free_port(),
                extra_env=env,
            )
            for i in (1, 0)
        ]
        bad = start(
            [*TINY, "distributed=true"],
            tmp_path / "bad",
            0,
            2,
            free_port(),
            extra_env={"COHERENT_JAX_INIT_TIMEOUT": "soon"},
        )
        procs = [*alone, bad]
        statuses = finish(procs, timeout=300)
        elapsed = time.monotonic() - t0
    finally:
        kill_all(procs)
    assert statuses == [4, 4, 2], [text(tmp_path / n, ".err")[-2000:] for n in ("p1", "p0", "bad")]
    for name in ("p1", "p0"):
        err = text(tmp_path / name, ".err")
        lines = [ln for ln in err.splitlines() if ln.strip() and "warp" not in ln]
        assert (
            len(lines) == 1 and "could not join the coordinator" in lines[0] and f"{INIT_S} s" in lines[0]
        ), err
    bad_err = text(tmp_path / "bad", ".err")
    assert "error: invalid value for COHERENT_JAX_INIT_TIMEOUT: 'soon'" in bad_err, bad_err
    # Nothing written: the run directory comes after joining.
    assert not (tmp_path / "r0").exists() and not (tmp_path / "r1").exists()
    assert elapsed < 120 + INIT_S, elapsed


def test_native_log_filter_holds_runtime_entries_and_names_the_cause(monkeypatch):
    """The supervisor passes other lines on, holds the runtime's log entries, and sums a fatal one up."""
    import io

    from coherent_jax.run.multihost import _NativeLog

    monkeypatch.setenv("JAX_PROCESS_ID", "0")
    monkeypatch.setenv("JAX_NUM_PROCESSES", "2")
    out = io.StringIO()
    log = _NativeLog(out)
    lines = [
        "[Gloo] Rank 0 is connected to 1 peer ranks.\n",
        "E1123 16:51:47.687327   17880 coordination_service.cc:1681] Use error polling to propagate the "
        "following error to all tasks: UNAVAILABLE: The following tasks are unhealthy "
        "(stopped sending heartbeats):\n",
        "1\n",
        "The tasks have crashed.\n",
        "F1123 16:51:47.687970   17891 client.h:80] Terminating process because the JAX distributed service "
        "detected fatal errors.\n",
        "*** Check failure stack trace: ***\n",
        "    @     0x7f31ac16afa4  absl::log_internal::LogMessage::SendToLog()\n",
    ]
    for line in lines:
        log.feed(line)
    assert out.getvalue() == lines[0]
    assert log.fatal
    summary = log.summary()
    assert "\n" not in summary
    assert summary.startswith("error: process 0 of 2: process 1 of the run stopped; every process stops")

    # A worker's own report of a failed collective wins over the runtime's guess.
    log = _NativeLog(io.StringIO())
    log.feed("coherent_jax: collective failed: Gloo all-reduce failed: Connection closed by peer\n")
    assert not log.fatal and "a collective with another process failed (Gloo all-reduce" in log.summary()

    # Entries of a process the runtime did not abort are written out at the end, unchanged.
    out = io.StringIO()
    log = _NativeLog(out)
    log.feed("W1123 16:51:47.000000   1 some.cc:1] a warning\n")
    log.feed("  its second line\n")
    assert out.getvalue() == "" and not log.fatal
    log.release()
    assert out.getvalue() == "W1123 16:51:47.000000   1 some.cc:1] a warning\n  its second line\n"
