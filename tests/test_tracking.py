"""The Weights & Biases mirror (coherent_jax.tracking), offline: what the local run files hold."""

import json

import pytest
from wandb_records import offline_runs, read_run

from coherent_jax import tracking

pytest.importorskip("wandb")


def test_offline_by_default_and_the_users_mode_wins(monkeypatch):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    assert tracking.mode() == "offline"
    monkeypatch.setenv("WANDB_MODE", "disabled")
    assert tracking.mode() == "disabled"


def test_rows_config_summary_and_resume_reach_the_local_run_files(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    config = {"env": "pointmass", "lr": 3e-4, "coherent": {"beta": 0.01}}
    run = tracking.WandbRun.open(tmp_path, config, name="point", group="sweep-x")
    rows = [{"env_steps": 64.0 * (i + 1), "train/loss": 1.0 / (i + 1), "eval/return": None} for i in range(3)]
    for i, row in enumerate(rows):
        run.log(row, step=i + 1)
    run.finish()
    identity = json.loads((tmp_path / tracking.RUN_FILE).read_text())

    # Resumed: the same W&B id, the rows after the checkpoint, then the final summary.
    run = tracking.WandbRun.open(tmp_path, config, name="point", group="sweep-x")
    run.log({"env_steps": 256.0, "train/loss": 0.25, "eval/return": -3.5}, step=4)
    run.finish({"final_eval_return": -3.5, "env_steps": 256})

    first, second = (read_run(p) for p in offline_runs(tmp_path))
    assert first["id"] == second["id"] == identity["id"]
    assert first["group"] == "sweep-x" and first["name"] == "point"
    assert first["config"] == config
    got = [{k: v for k, v in h.items() if not k.startswith("_")} for h in first["history"]]
    assert got == [{k: v for k, v in r.items() if v is not None} for r in rows]
    assert [h["_step"] for h in first["history"]] == [1, 2, 3]
    assert second["history"][-1]["eval/return"] == -3.5 and second["history"][-1]["_step"] == 4
    assert second["summary"]["final_eval_return"] == -3.5 and second["summary"]["env_steps"] == 256


def test_missing_package_is_one_line_with_the_install_command(monkeypatch):
    monkeypatch.setattr(tracking, "available", lambda: False)
    with pytest.raises(tracking.TrackingError, match=r'^wandb=true needs .*pip install -e "\.\[wandb\]"$'):
        tracking.require()
