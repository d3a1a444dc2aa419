"""End to end: the real config with fast overrides, learning thresholds, reproducibility."""

import json

import numpy as np
import pytest

from coherent_jax.config import parse_overrides
from coherent_jax.run.training import train
from coherent_jax.train import main

FAST = [
    "env=pointmass",
    "num_envs=32",
    "unroll_length=32",
    "ppo.num_minibatches=4",
    "eval_episodes=4",
    "progress=false",
]


def read_rows(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def strip_times(rows):
    return [{k: v for k, v in r.items() if k != "time_s"} for r in rows]


@pytest.mark.slow
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
    "algo,extra",
    [
        ("ppo", ["total_steps=81920", "eval_every=8"]),
        ("ppo", ["total_steps=40960", "eval_every=5", "explore=coherent"]),
        ("a2c", ["total_steps=163840", "eval_every=32", "unroll_length=8", "lr=3e-3", "explore=coherent"]),
    ],
)
def test_learns_inverted_pendulum(algo, extra):
    """The policy balances the pole: a deterministic eval return of at least 500 during
    training, far above an untrained policy's (about 35-55; 1000 is the maximum).

    The best evaluation, not the last: on this task PPO and A2C solve it and then often lose
    it again for a while, so the last evaluation alone depends on float rounding. Measured
    over seeds 0-5 with XLA's AVX2 and AVX-512 code (`XLA_FLAGS=--xla_cpu_max_isa=...`): the
    last evaluation was below 500 in 4 of 12 runs for PPO at 81,920 steps (PPO at 40,960:
    in 4 of 8), while every run reached 1000 at some evaluation in these settings.
    A2C with coherent exploration learns later: at 81,920 steps its best evaluation
    reached 500 in only 3 of 6 runs (seeds 0-2, both ISAs; 79, 84 and 187 in the
    others), at 163,840 steps in 6 of 6 (the lowest best 834, AVX2 seed 0).

    Brax's re-creation, on which these budgets were set: Gymnasium's InvertedPendulum-v5
    (`env=inverted_pendulum`) is a different task (RK4, no reward on the falling step)."""
    cfg = parse_overrides([*FAST, "env=brax-inverted_pendulum", f"algo={algo}", "eval_episodes=8", *extra])
    history = []
    summary = train(cfg, None, progress_fn=lambda i, m: history.append(m))
    assert all(np.isfinite(m["train/value_loss"]) for m in history)
    evals = [m["eval/episode_return"] for m in history if "eval/episode_return" in m]
    assert len(evals) == cfg.total_steps // (cfg.num_envs * cfg.unroll_length * cfg.eval_every)
    assert evals[-1] == summary["final_eval_return"]
    print(f"{algo} {extra}: eval returns {[round(e) for e in evals]}")
    assert max(evals) >= 500.0
