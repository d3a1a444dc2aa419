"""End to end: the real config with fast overrides, learning thresholds, reproducibility."""

import json

import numpy as np
import pytest

from coherent_jax.config import parse_overrides
from coherent_jax.train import main, train

FAST = [
    "env=pointmass",
    "num_envs=32",
    "unroll_length=32",
    "num_minibatches=4",
    "eval_episodes=4",
    "progress=false",
]


def read_rows(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def strip_times(rows):
    return [{k: v for k, v in r.items() if k != "time_s"} for r in rows]


def test_cli_run_writes_run_dir_and_is_reproducible(tmp_path):
    """A CLI run writes config, metrics, params and summary; the same seed twice is identical."""
    run = tmp_path / "run"
    assert main([*FAST, "total_steps=3072", "eval_every=2", "seed=3", f"run_dir={run}"]) == 0
    assert sorted(p.name for p in run.iterdir()) == [
        "checkpoint.msgpack",
        "config.yaml",
        "metrics.jsonl",
        "params.msgpack",
        "summary.json",
        "tb",
        "versions.json",
    ]
    rows = read_rows(run / "metrics.jsonl")
    assert [r["iteration"] for r in rows] == [1, 2, 3]
    assert [r["env_steps"] for r in rows] == [1024, 2048, 3072]
    assert "eval/episode_return" in rows[1] and "eval/episode_return" not in rows[0]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["env_steps"] == 3072 and summary["compile_s"] > 0
    assert "seed: 3" in (run / "config.yaml").read_text()

    run2 = tmp_path / "run2"
    assert main([*FAST, "total_steps=3072", "eval_every=2", "seed=3", f"run_dir={run2}"]) == 0
    assert strip_times(read_rows(run2 / "metrics.jsonl")) == strip_times(rows)

    run3 = tmp_path / "run3"
    assert main([*FAST, "total_steps=3072", "eval_every=2", "seed=4", f"run_dir={run3}"]) == 0
    assert strip_times(read_rows(run3 / "metrics.jsonl")) != strip_times(rows)


@pytest.mark.slow
@pytest.mark.parametrize(
    "algo,extra,threshold",
    [
        ("ppo", ["total_steps=40960"], 500.0),
        ("ppo", ["total_steps=40960", "explore=coherent"], 500.0),
        # Coherent-A2C solved this in 2 of 2 seeds at this budget; action-noise A2C
        # solved it in 1 of 6 runs across seeds and learning rates (README, Figures).
        ("a2c", ["total_steps=81920", "unroll_length=8", "lr=3e-3", "explore=coherent"], 500.0),
    ],
)
def test_learns_inverted_pendulum(algo, extra, threshold):
    """Deterministic eval return far above an untrained policy's (about 35-55).

    Brax's re-creation, on which these budgets were set: Gymnasium's InvertedPendulum-v5
    (`env=inverted_pendulum`) is a different task (RK4, no reward on the falling step) that
    PPO had not solved at 40,960 steps (eval return 90)."""
    cfg = parse_overrides(
        [*FAST, "env=brax-inverted_pendulum", f"algo={algo}", "eval_every=0", "eval_episodes=8", *extra]
    )
    history = []
    summary = train(cfg, None, progress_fn=lambda i, m: history.append(m))
    assert all(np.isfinite(m["train/value_loss"]) for m in history)
    print(f"{algo} {extra}: final eval return {summary['final_eval_return']:.1f}")
    assert summary["final_eval_return"] >= threshold
