"""Long runs: kill-and-resume equality, signals, the divergence guard, refused bad input.

Every run here is `pointmass` with tiny networks (a few seconds to compile); the
kill is a real SIGKILL of a training subprocess.
"""

import hashlib
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import child_env, tensorboard_scalars

from coherent_jax.config import parse_overrides
from coherent_jax.run.checkpoint import CHECKPOINT, LoopState, decode_checkpoint, encode_checkpoint
from coherent_jax.run.rundir import atomic_write, read_metrics, truncate_metrics
from coherent_jax.study import carry
from coherent_jax.train import main

TINY = [
    "env=pointmass",
    "algo=a2c",
    "num_envs=2",
    "ppo.num_minibatches=1",
    "unroll_length=4",
    "eval_episodes=2",
    "episode_length=20",
    "policy_hidden=[8]",
    "value_hidden=[8]",
    "progress=false",
]
# 150 iterations: long enough to be interrupted twice, short enough to run to the end.
LONG = [*TINY, "total_steps=1200", "eval_every=7", "checkpoint_every=3", "seed=5"]
ROOT = Path(__file__).resolve().parents[1]


def strip_times(rows):
    return [{k: v for k, v in r.items() if k != "time_s"} for r in rows]


def spawn(args, cwd, module="coherent_jax.train"):
    env = child_env()
    return subprocess.Popen(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def wait_for_rows(proc, metrics, n, timeout=300.0):
    """Polls until `metrics` holds at least `n` complete rows (the process still running)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        assert proc.poll() is None, f"run ended before it could be interrupted: {proc.communicate()}"
        if metrics.exists() and len(read_metrics(metrics)) >= n:
            return
        time.sleep(0.002)
    raise AssertionError("no progress")


def snapshot(path: Path) -> dict[str, str]:
    return {
        str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(path.rglob("*"))
        if p.is_file()
    }


@pytest.mark.slow
def test_sigkill_then_resume_equals_an_uninterrupted_run(tmp_path, monkeypatch):
    """SIGKILL mid-run, move the directory, resume it from elsewhere: metrics and parameters
    equal an uninterrupted run's. Then ``total_steps`` extends the finished run."""
    first = tmp_path / "first"
    proc = spawn([*LONG, f"run_dir={first}"], tmp_path)
    wait_for_rows(proc, first / "metrics.jsonl", 10)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = len(read_metrics(first / "metrics.jsonl"))
    ckpt = decode_checkpoint(first / CHECKPOINT, parse_overrides(LONG))
    assert 10 <= killed_at < 150 and ckpt.iteration % 3 == 0 and ckpt.iteration <= killed_at
    assert not (first / "summary.json").exists()

    # Moved, and resumed by a relative path from another working directory.
    run = tmp_path / "moved" / "run"
    run.parent.mkdir()
    first.rename(run)
    metrics = run / "metrics.jsonl"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main(["resume=../moved/run"]) == 0
    resumed = read_metrics(metrics)
    assert [r["iteration"] for r in resumed] == list(range(1, 151))
    assert json.loads((run / "summary.json").read_text())["resumed_from"] == ckpt.iteration

    ref = tmp_path / "ref"
    assert main([*LONG, f"run_dir={ref}"]) == 0
    reference = read_metrics(ref / "metrics.jsonl")
    assert len(reference) == 150 and any("eval/episode_return" in r for r in reference)
    assert strip_times(resumed) == strip_times(reference)
    assert (run / "params.msgpack").read_bytes() == (ref / "params.msgpack").read_bytes()
    rewards = tensorboard_scalars(run / "tb")["train/reward_mean"]
    assert sorted(rewards) == [r["env_steps"] for r in reference]
    assert rewards[reference[-1]["env_steps"]] == pytest.approx(reference[-1]["train/reward_mean"], rel=1e-6)
    assert json.loads((run / "versions.json").read_text())["jax"] == "0.9.2"

    # A finished run resumed again is left alone.
    before = snapshot(run)
    assert main([f"resume={run}"]) == 0
    assert snapshot(run) == before

    # A larger budget extends it: the first 150 rows stay, 10 more follow.
    assert main([f"resume={run}", "total_steps=1280"]) == 0
    extended = read_metrics(metrics)
    assert [r["iteration"] for r in extended] == list(range(1, 161))
    assert strip_times(extended[:150]) == strip_times(reference)
    assert json.loads((run / "summary.json").read_text())["env_steps"] == 1280
    assert "total_steps: 1280" in (run / "config.yaml").read_text()
    # A budget below the work already done is refused.
    assert main([f"resume={run}", "total_steps=400"]) == 2


@pytest.mark.slow
def test_sigterm_stops_after_the_iteration_with_a_checkpoint(tmp_path):
    """SIGTERM: exit 128+15 after finishing the iteration, whose checkpoint is the last row's."""
    run = tmp_path / "run"
    metrics = run / "metrics.jsonl"
    args = [*(a for a in LONG if not a.startswith("checkpoint_every=")), "checkpoint_every=1000"]
    proc = spawn([*args, f"run_dir={run}"], tmp_path)
    wait_for_rows(proc, metrics, 5)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "stopped by SIGTERM" in out and "resume=" in out
    assert out.index("compiling ...") < out.index("compiled in")
    assert "Failed to import" not in out + err  # mujoco's message about its optional warp backend
    rows = read_metrics(metrics)
    ckpt = decode_checkpoint(run / CHECKPOINT, parse_overrides(args))
    assert ckpt.iteration == rows[-1]["iteration"] == len(rows) < 150
    assert not (run / "summary.json").exists() and not (run / "params.msgpack").exists()


@pytest.mark.slow
def test_a_sweep_stopped_before_its_first_evaluation_and_carried_resumes_to_the_uninterrupted_one(tmp_path):
    """SIGTERM to a vmapped sweep before any evaluation: exit 128+15 with no traceback and no
    sweep.json. Carried as a study carries a cell to another checkout (packed,
    the sweep directory deleted, unpacked) and resumed, every point's metrics equal those of a
    sweep never stopped."""
    cell = tmp_path / "cell"
    sweep = cell / "sweep"
    args = [*(a for a in LONG if not a.startswith(("eval_every=", "checkpoint_every="))), "seeds=2"]
    args += ["eval_every=1000", "checkpoint_every=1000"]
    proc = spawn([*args, f"run_dir={sweep}"], tmp_path, "coherent_jax.sweep")
    points = ("p000-seed=5", "p001-seed=6")  # LONG: seed=5
    wait_for_rows(proc, sweep / points[0] / "metrics.jsonl", 5)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "Traceback" not in err and "stopped by SIGTERM" in out, err
    rows = read_metrics(sweep / points[0] / "metrics.jsonl")
    assert 5 <= len(rows) < 150 and not any("eval/episode_return" in r for r in rows)
    assert not (sweep / "sweep.json").exists()
    carry.pack(cell)
    shutil.rmtree(sweep)
    assert carry.unpack(cell)

    from coherent_jax.sweep import main as sweep_main

    assert sweep_main([f"resume={sweep}"]) == 0
    ref = tmp_path / "ref"
    assert sweep_main([*args, f"run_dir={ref}"]) == 0
    for point in points:
        resumed = strip_times(read_metrics(sweep / point / "metrics.jsonl"))
        assert len(resumed) == 150 and resumed == strip_times(read_metrics(ref / point / "metrics.jsonl"))
        assert json.loads((sweep / point / "summary.json").read_text())["final_eval_return"] is not None


def test_divergence_stops_naming_iteration_and_quantity(tmp_path, capsys):
    """A learning rate of 1e30 makes the loss NaN at iteration 2; the run stops, checkpoint 1 stays."""
    run = tmp_path / "run"
    args = [*TINY, "total_steps=400", "checkpoint_every=1", "lr=1e30", f"run_dir={run}"]
    assert main(args) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: diverged at iteration 2: "), err
    assert "loss" in err[0] or "parameter" in err[0]
    assert "last good checkpoint: iteration 1" in err[0]
    assert decode_checkpoint(run / CHECKPOINT, parse_overrides(args)).iteration == 1
    assert len(read_metrics(run / "metrics.jsonl")) == 1
    assert not (run / "params.msgpack").exists()


def test_guard_skips_losses_of_an_iteration_without_update_but_never_parameters():
    """SAC logs NaN losses while its buffer warms up (no update applied): not a divergence."""
    import jax.numpy as jnp

    from coherent_jax.run.loop import check_finite as _check_finite
    from coherent_jax.run.loop_state import DivergenceError

    class Trainer:
        def export_params(self, state):
            return state

    params = {"actor": {"w": jnp.array([1.0, jnp.inf])}, "obs_stats": jnp.zeros(2)}
    warmup = {"train/actor_loss": float("nan"), "train/updates_applied": 0.0}
    _check_finite(3, warmup, True, params, Trainer(), None, 0)
    with pytest.raises(DivergenceError, match=r"iteration 3: train/actor_loss = nan"):
        _check_finite(3, {**warmup, "train/updates_applied": 4.0}, True, params, Trainer(), None, 0)
    with pytest.raises(DivergenceError, match=r"iteration 7: parameter \['actor'\]\['w'\] is not finite"):
        _check_finite(7, warmup, False, params, Trainer(), None, 0)
    # NaN in a metric that is not a loss (no episode ended) is not a divergence.
    _check_finite(
        8, {"train/episode_return": float("nan"), "train/policy_loss": 0.1}, True, params, Trainer(), None, 0
    )


def test_truncate_metrics_drops_rows_past_the_checkpoint_and_a_partial_line(tmp_path):
    path = tmp_path / "metrics.jsonl"
    rows = [{"iteration": i, "x": i * 0.5} for i in range(1, 6)]
    path.write_text("".join(json.dumps(r) + "\n" for r in rows) + '{"iteration": 6, "x"')
    assert read_metrics(path) == rows
    truncate_metrics(path, 3)
    assert path.read_text() == "".join(json.dumps(r) + "\n" for r in rows[:3])


# ---------------------------------------------------------------- bad input
FAKE = [*TINY, "total_steps=400", "seed=1"]


@pytest.fixture
def fake_run(tmp_path):
    """A run directory as the CLI leaves it, with a synthetic (unrestorable) checkpoint.

    Every refusal below happens before the state is restored, so no compile is needed.
    """
    from omegaconf import OmegaConf

    from coherent_jax.config import to_dict

    cfg = parse_overrides(FAKE)
    run = tmp_path / "run"
    run.mkdir()
    atomic_write(run / "config.yaml", OmegaConf.to_yaml(to_dict(cfg)).encode())
    atomic_write(run / "metrics.jsonl", b'{"iteration": 1, "env_steps": 8}\n')
    blob = encode_checkpoint(cfg, 1, 8, LoopState(eval_key=[0, 1]), b"\x81\xa1a\x01" * 64)
    atomic_write(run / CHECKPOINT, blob)
    return run


def refused(args, capsys, key_text, run=None):
    before = snapshot(run) if run is not None else None
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and key_text in err[0], err
    if run is not None:
        assert snapshot(run) == before, "a refused resume changed the run directory"
    return err[0]


def test_synthetic_checkpoint_round_trips(fake_run):
    ckpt = decode_checkpoint(fake_run / CHECKPOINT, parse_overrides(FAKE))
    assert ckpt.iteration == 1 and ckpt.loop.eval_key == [0, 1]


def test_truncated_checkpoint_is_refused_untouched(fake_run, capsys):
    path = fake_run / CHECKPOINT
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    refused([f"resume={fake_run}"], capsys, "truncated", fake_run)


def test_corrupted_checkpoint_is_refused_untouched(fake_run, capsys):
    path = fake_run / CHECKPOINT
    data = bytearray(path.read_bytes())
    data[-80] ^= 0xFF  # one flipped byte inside the state
    path.write_bytes(bytes(data))
    refused([f"resume={fake_run}"], capsys, "sha256", fake_run)


def test_foreign_checkpoint_is_refused_untouched(fake_run, tmp_path, capsys):
    """A checkpoint copied from a run with another config (seed 2) into this run's directory."""
    other = parse_overrides([*TINY, "total_steps=400", "seed=2"])
    atomic_write(fake_run / CHECKPOINT, encode_checkpoint(other, 1, 8, LoopState(eval_key=[0, 1]), b"x"))
    refused([f"resume={fake_run}"], capsys, "another run", fake_run)


def test_resume_with_changed_config_is_refused(fake_run, capsys):
    msg = refused([f"resume={fake_run}", "lr=0.1"], capsys, "'lr'", fake_run)
    assert "the run's own value" in msg


def test_resume_with_malformed_override_is_refused(fake_run, capsys):
    refused([f"resume={fake_run}", "lr"], capsys, "'lr'", fake_run)


def test_resume_from_missing_or_foreign_directory_is_refused(tmp_path, capsys):
    refused([f"resume={tmp_path / 'nowhere'}"], capsys, "'resume'")
    stranger = tmp_path / "stranger"
    stranger.mkdir()
    (stranger / "notes.txt").write_text("not a run")
    refused([f"resume={stranger}"], capsys, "config.yaml", stranger)


def test_resume_with_nan_in_stored_config_is_refused(fake_run, capsys):
    path = fake_run / "config.yaml"
    path.write_text(path.read_text().replace("lr: 0.0003", "lr: .nan"))
    refused([f"resume={fake_run}"], capsys, "'lr'", fake_run)


def test_missing_checkpoint_is_refused(fake_run, capsys):
    """Rows for a whole checkpoint interval (10) but no checkpoint: it was lost, not yet to be written."""
    (fake_run / CHECKPOINT).unlink()
    rows = "".join(json.dumps({"iteration": i, "env_steps": 8 * i}) + "\n" for i in range(1, 11))
    (fake_run / "metrics.jsonl").write_text(rows)
    refused([f"resume={fake_run}"], capsys, "no checkpoint", fake_run)


def test_resume_with_malformed_stored_yaml_is_refused(fake_run, capsys):
    path = fake_run / "config.yaml"
    path.write_text(path.read_text().replace("policy_hidden:", "policy_hidden: [8,\n  oops:"))
    refused([f"resume={fake_run}"], capsys, "not valid YAML", fake_run)


SHORT = [*TINY, "total_steps=80", "eval_every=3", "checkpoint_every=4", "seed=2"]


@pytest.mark.slow
def test_ctrl_c_during_compile_and_kill_before_first_checkpoint_are_resumable(tmp_path):
    """SIGINT while compiling: exit 130, no traceback, a checkpoint at iteration 0 that resumes to an
    uninterrupted run's metrics. A run killed before any checkpoint (none written) starts over."""
    run = tmp_path / "run"
    proc = spawn([*SHORT, f"run_dir={run}"], tmp_path)
    for line in proc.stdout:
        if "compiling" in line:
            break
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGINT, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert decode_checkpoint(run / CHECKPOINT, parse_overrides(SHORT)).iteration == 0
    assert read_metrics(run / "metrics.jsonl") == []

    bare = tmp_path / "bare"  # what a SIGKILL during the compile leaves: no checkpoint, no rows
    bare.mkdir()
    for name in ("config.yaml", "versions.json"):
        (bare / name).write_bytes((run / name).read_bytes())

    assert main([f"resume={run}"]) == 0
    assert main([f"resume={bare}"]) == 0
    ref = tmp_path / "ref"
    assert main([*SHORT, f"run_dir={ref}"]) == 0
    reference = strip_times(read_metrics(ref / "metrics.jsonl"))
    assert [r["iteration"] for r in reference] == list(range(1, 11))
    assert strip_times(read_metrics(run / "metrics.jsonl")) == reference
    assert strip_times(read_metrics(bare / "metrics.jsonl")) == reference


SAC_LONG = [
    *(a for a in LONG if not a.startswith(("algo=", "num_envs=", "ppo.", "checkpoint_every="))),
    "algo=sac",
    "explore=coherent",
    "num_envs=2",
    "sac.buffer_size=256",
    "sac.batch_size=8",
    "sac.warmup_steps=64",
    "checkpoint_every=1000",
    "seeds=2",
]


@pytest.mark.slow
def test_an_sac_sweep_stopped_after_its_buffer_wrapped_resumes_to_the_uninterrupted_one(tmp_path):
    """SIGTERM to a vmapped Coherent-SAC sweep after the replay ring buffer has wrapped and
    updates have begun; resumed, every point's metrics and parameters equal those of a sweep
    never stopped. The checkpoint must hold the buffer (contents, position, size), the
    chain's state and the optimiser's, or the resumed run departs from the reference."""
    from coherent_jax.sweep import main as sweep_main

    sweep = tmp_path / "sweep"
    points = ("p000-seed=5", "p001-seed=6")  # LONG: seed=5
    proc = spawn([*SAC_LONG, f"run_dir={sweep}"], tmp_path, "coherent_jax.sweep")
    # 8 env steps per iteration: the 256-slot buffer has wrapped after iteration 32.
    wait_for_rows(proc, sweep / points[0] / "metrics.jsonl", 40)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    stopped_at = len(read_metrics(sweep / points[0] / "metrics.jsonl"))
    assert 40 <= stopped_at < 150 and not (sweep / "sweep.json").exists()

    assert sweep_main([f"resume={sweep}"]) == 0
    ref = tmp_path / "ref"
    assert sweep_main([*SAC_LONG, f"run_dir={ref}"]) == 0
    for point in points:
        reference = strip_times(read_metrics(ref / point / "metrics.jsonl"))
        assert len(reference) == 150 and any("eval/episode_return" in r for r in reference)
        assert strip_times(read_metrics(sweep / point / "metrics.jsonl")) == reference
        params = (sweep / point / "params.msgpack").read_bytes()
        assert params == (ref / point / "params.msgpack").read_bytes()
