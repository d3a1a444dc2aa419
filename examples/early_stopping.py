"""Stop training early once the evaluation return reaches a threshold (docs/api.md, Callbacks).

    python examples/early_stopping.py [--threshold R] [--run-dir DIR]

Trains PPO on ``pointmass`` (the analytic test task, which compiles fastest) with a budget of
200 iterations, evaluating every 2, and a callback that stops the run at the first evaluation
whose mean return reaches ``--threshold`` (default -20; the untrained policy scores about -30 to -50). The
stop writes a checkpoint, so ``resume=DIR`` (here: ``coherent_jax.learn({"resume": DIR})``)
would continue the same run; the summary says why it stopped.
"""

from __future__ import annotations

import argparse
import math
import tempfile

import coherent_jax


class StopAtReturn(coherent_jax.Callback):
    """Stops at the first evaluation whose mean return is at least `threshold`."""

    def __init__(self, threshold: float) -> None:
        self.threshold = threshold
        self.evaluations: list[tuple[int, float]] = []

    def on_evaluation(self, row):
        ret = row["eval/episode_return"]
        self.evaluations.append((row["iteration"], math.nan if ret is None else ret))

    def on_iteration(self, row):
        ret = row.get("eval/episode_return")
        if ret is not None and ret >= self.threshold:
            return coherent_jax.Stop(f"eval return {ret:.1f} >= {self.threshold} at {row['iteration']}")
        return None


def main(threshold: float = -20.0, run_dir: str | None = None) -> coherent_jax.TrainResult:
    stopper = StopAtReturn(threshold)
    cfg = coherent_jax.make_config(
        env="pointmass",
        num_envs=16,
        unroll_length=32,
        episode_length=40,
        total_steps=200 * 16 * 32,
        eval_every=2,
        eval_episodes=8,
        policy_hidden=[32, 32],
        value_hidden=[32, 32],
        run_dir=run_dir or tempfile.mkdtemp(prefix="early-stopping-"),
        progress=False,
        tensorboard=False,
    )
    result = coherent_jax.learn(cfg, callbacks=[stopper])
    print("evaluations (iteration, return):", [(i, round(r, 1)) for i, r in stopper.evaluations])
    print(f"stopped_by={result.stopped_by}: {result.summary.get('stop_reason')}")
    print(f"{result.summary['iterations']} of 200 iterations; continue with resume={result.run_dir}")
    return result


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--threshold", type=float, default=-20.0)
    parser.add_argument("--run-dir", default=None)
    args = parser.parse_args()
    main(args.threshold, args.run_dir)
