"""Log a run's rows to a sink of your own, here a CSV file (docs/api.md, Callbacks).

    python examples/custom_logger.py [--csv FILE] [--run-dir DIR]

Trains PPO on ``pointmass`` for 10 iterations with a callback that writes one CSV row per
iteration (its iteration, env steps and training return, and the evaluation return where
there is one), the same values ``metrics.jsonl`` holds, then prints the file.
"""

from __future__ import annotations

import argparse
import csv
import tempfile
from pathlib import Path

import coherent_jax

COLUMNS = ["iteration", "env_steps", "train/episode_return", "eval/episode_return"]


class CsvLogger(coherent_jax.Callback):
    """Appends `COLUMNS` of every row to a CSV file (empty where a row has no value)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def on_start(self, info):
        new = info.start_iteration == 0 or not self.path.exists()
        self.file = open(self.path, "w" if new else "a", newline="")
        self.writer = csv.DictWriter(self.file, COLUMNS, extrasaction="ignore")
        if new:
            self.writer.writeheader()

    def on_iteration(self, row):
        self.writer.writerow({k: row.get(k) for k in COLUMNS})
        self.file.flush()

    def on_end(self, summary):
        self.file.close()


def main(csv_path: str | None = None, run_dir: str | None = None) -> Path:
    out = Path(csv_path or Path(tempfile.mkdtemp(prefix="custom-logger-")) / "rows.csv")
    cfg = coherent_jax.make_config(
        env="pointmass",
        num_envs=8,
        unroll_length=16,
        episode_length=40,
        total_steps=10 * 8 * 16,
        eval_every=5,
        policy_hidden=[16, 16],
        value_hidden=[16, 16],
        run_dir=run_dir or tempfile.mkdtemp(prefix="custom-logger-run-"),
        progress=False,
        tensorboard=False,
    )
    coherent_jax.learn(cfg, callbacks=[CsvLogger(out)])
    print(out.read_text(), end="")
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--csv", default=None)
    parser.add_argument("--run-dir", default=None)
    args = parser.parse_args()
    main(args.csv, args.run_dir)
