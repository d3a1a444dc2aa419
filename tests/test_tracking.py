"""The Weights & Biases mirror (coherent_jax.run.outputs), offline: what the local run files hold."""

import json

import pytest
from wandb_records import offline_runs, read_run

from coherent_jax.run import outputs

pytest.importorskip("wandb")


def test_offline_by_default_and_the_users_mode_wins(monkeypatch):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    assert outputs.wandb_mode() == "offline"
    monkeypatch.setenv("WANDB_MODE", "disabled")
    assert outputs.wandb_mode() == "disabled"


def test_rows_config_summary_and_resume_reach_the_local_run_files(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    config = {"env": "pointmass", "lr": 3e-4, "coherent": {"beta": 0.01}}
    run = outputs.WandbRun.open(tmp_path, config, name="point", group="sweep-x")
    rows = [{"env_steps": 64.0 * (i + 1), "train/loss": 1.0 / (i + 1), "eval/return": None} for i in range(3)]
    for i, row in enumerate(rows):
        run.log(row, step=i + 1)
    run.finish()
    identity = json.loads((tmp_path / outputs.WANDB_RUN_FILE).read_text())

    # Resumed: the same W&B id, the rows after the checkpoint, then the final summary.
    run = outputs.WandbRun.open(tmp_path, config, name="point", group="sweep-x")
    run.log({"env_steps": 256.0, "train/loss": 0.25, "eval/return": -3.5}, step=4)
    run.finish({"final_eval_return": -3.5, "env_steps": 256})

    first, second = (read_run(p) for p in offline_runs(tmp_path, expected=2))
    assert first["id"] == second["id"] == identity["id"]
    assert first["group"] == "sweep-x" and first["name"] == "point"
    assert first["config"] == config
    got = [{k: v for k, v in h.items() if not k.startswith("_")} for h in first["history"]]
    assert got == [{k: v for k, v in r.items() if v is not None} for r in rows]
    assert [h["_step"] for h in first["history"]] == [1, 2, 3]
    assert second["history"][-1]["eval/return"] == -3.5 and second["history"][-1]["_step"] == 4
    assert second["summary"]["final_eval_return"] == -3.5 and second["summary"]["env_steps"] == 256


def test_missing_package_is_one_line_with_the_install_command(monkeypatch):
    monkeypatch.setattr(outputs, "wandb_available", lambda: False)
    with pytest.raises(outputs.TrackingError, match=r'^wandb=true needs .*pip install -e "\.\[wandb\]"$'):
        outputs.require_wandb()


TINY = [
    "env=pointmass",
    "num_envs=8",
    "unroll_length=16",
    "episode_length=40",
    "eval_every=2",
    "eval_episodes=4",
    "policy_hidden=[16,16]",
    "value_hidden=[16,16]",
    "ppo.num_epochs=2",
    "ppo.num_minibatches=2",
    "progress=false",
    "tensorboard=false",
    "checkpoint_every=1",
    "wandb=true",
]


def _rows(run_dir):
    """metrics.jsonl's rows as W&B holds them: None (not finite) left out."""
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [{k: v for k, v in r.items() if v is not None} for r in rows]


def _history(record):
    return [{k: v for k, v in h.items() if not k.startswith("_")} for h in record["history"]]


@pytest.mark.slow
def test_a_run_mirrors_its_config_rows_and_summary_and_a_resume_continues_the_same_run(tmp_path, monkeypatch):
    import yaml

    from coherent_jax.train import main

    monkeypatch.delenv("WANDB_MODE", raising=False)
    run = tmp_path / "run"
    assert main([*TINY, "total_steps=256", f"run_dir={run}"]) == 0  # 2 iterations
    first_rows = _rows(run)
    first_summary = json.loads((run / "summary.json").read_text())
    assert main([f"resume={run}", "total_steps=384"]) == 0  # extended: iteration 3
    identity = json.loads((run / outputs.WANDB_RUN_FILE).read_text())
    assert identity["name"] == "run" and identity["group"] is None

    first, second = (read_run(p) for p in offline_runs(run, expected=2))
    assert first["id"] == second["id"] == identity["id"]
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert second["config"] == config and first["config"] == {**config, "total_steps": 256}
    assert config["wandb"] is True
    assert _history(first) == first_rows and [h["_step"] for h in first["history"]] == [1, 2]
    assert _history(second) == _rows(run)[2:] and [h["_step"] for h in second["history"]] == [3]
    assert first_rows == _rows(run)[:2]
    assert {k: first["summary"][k] for k in first_summary} == first_summary
    summary = json.loads((run / "summary.json").read_text())
    assert summary["resumed_from"] == 2 and {k: second["summary"][k] for k in summary} == summary


@pytest.mark.slow
def test_a_sweep_gives_one_run_per_point_grouped_by_the_sweep(tmp_path, monkeypatch):
    import yaml

    from coherent_jax.sweep import main

    monkeypatch.delenv("WANDB_MODE", raising=False)
    out = tmp_path / "sweep"
    assert main([*TINY, "total_steps=256", "seeds=2", "ppo.clip_eps=[0.1,0.3]", f"run_dir={out}"]) == 0
    points = sorted(d for d in out.iterdir() if d.is_dir() and d.name.startswith("p"))
    assert len(points) == 4
    records = []
    for point in points:
        (path,) = offline_runs(point)
        records.append(read_run(path))
        rec = records[-1]
        assert rec["group"] == "sweep" and rec["name"] == point.name
        assert rec["config"] == yaml.safe_load((point / "config.yaml").read_text())
        assert _history(rec) == _rows(point)
        summary = json.loads((point / "summary.json").read_text())
        assert {k: rec["summary"][k] for k in summary} == summary
    assert len({r["id"] for r in records}) == 4
    assert [r["config"]["ppo"]["clip_eps"] for r in records] == [0.1, 0.1, 0.3, 0.3]


@pytest.mark.parametrize("command", ["train", "sweep"])
def test_wandb_without_the_package_is_one_line_exit_2_and_nothing_written(
    tmp_path, monkeypatch, capsys, command
):
    import importlib

    main = importlib.import_module(f"coherent_jax.{command}").main
    monkeypatch.setattr(outputs, "wandb_available", lambda: False)
    assert main([*TINY, f"run_dir={tmp_path / 'run'}"]) == 2
    err = capsys.readouterr().err
    assert err == f"error: {outputs.WANDB_INSTALL_HINT}\n"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_evaluate_adds_its_video_to_the_runs_wandb_run(tmp_path, monkeypatch):
    import subprocess
    import sys

    from helpers import child_env
    from test_evaluate import make_zero_run

    monkeypatch.delenv("WANDB_MODE", raising=False)
    run = make_zero_run(
        tmp_path / "run",
        ["env=inverted_pendulum", "num_envs=1", "ppo.num_minibatches=1", "episode_length=10", "wandb=true"],
    )
    video = tmp_path / "out.gif"
    proc = subprocess.run(
        [sys.executable, "-m", "coherent_jax.evaluate", str(run), "episodes=1", "video=true"]
        + [f"video_path={video}", "width=32", "height=24"],
        env=child_env(),
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    (path,) = offline_runs(run)
    record = read_run(path)
    assert record["id"] == json.loads((run / outputs.WANDB_RUN_FILE).read_text())["id"]
    (row,) = [h for h in record["history"] if "eval/video/_type" in h]
    assert row["eval/video/_type"] == "video-file" and row["eval/video/path"].endswith(".gif")
    assert (path.parent / "files" / row["eval/video/path"]).read_bytes() == video.read_bytes()
