"""Train from Python, read the run, and act with its policy (docs/api.md).

    python examples/train_and_act.py [--run-dir DIR] [--total-steps N]

Trains PPO with coherent exploration on ``pointmass`` (the analytic test task, which
compiles fastest), prints the evaluation returns the run logged, then loads the policy
back from the run directory and steps the task with it from Python, one numpy
observation batch at a time: the deterministic episodes an evaluation runs.

Each run writes a new directory, ``runs/example-pointmass-<time>`` (``-2``, ``-3``, ...
if that exists), so the example can be run again and again; ``--run-dir`` names one,
which must be new or empty. ``--total-steps`` sets the budget (default 20,480: 10
iterations of 32 envs x 64 steps; ``--total-steps 2048`` is one iteration).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import coherent_jax


def fresh_run_dir(root: Path = Path("runs"), stamp: str | None = None) -> Path:
    """A run directory that does not exist yet: ``ROOT/example-pointmass-<time>``, with
    ``-2``, ``-3``, ... added when a run of the same second has it."""
    base = root / f"example-pointmass-{stamp or time.strftime('%Y%m%d-%H%M%S')}"
    path, n = base, 1
    while path.exists():
        n += 1
        path = base.with_name(f"{base.name}-{n}")
    return path


def main(run_dir: str | None = None, total_steps: int = 20_480) -> None:
    cfg = coherent_jax.make_config(
        env="pointmass",
        explore="coherent",
        total_steps=total_steps,
        num_envs=32,
        eval_every=2,
        run_dir=str(run_dir or fresh_run_dir()),
        progress=False,
        **{"coherent.beta": 0.1},
    )
    result = coherent_jax.learn(cfg)
    for row in result.metrics:
        if row.get("eval/episode_return") is not None:
            print(
                f"iteration {row['iteration']:3d}, {row['env_steps']:6d} env steps: "
                f"eval return {row['eval/episode_return']:8.2f}"
            )
    print(f"final eval return {result.summary['final_eval_return']:.2f}; run in {result.run_dir}")

    # Any run directory, at any later time: obs -> mean action, numpy in and out (needs JAX).
    policy = coherent_jax.load_policy(result.run_dir)
    returns = rollout(policy, episodes=4, seed=0)
    print(f"4 episodes stepped from Python: mean return {returns.mean():.2f}")


def rollout(policy, episodes: int, seed: int) -> np.ndarray:
    """Deterministic episodes of the policy on the task's own vectorised env."""
    import jax

    from coherent_jax.envs.vec_env import VecEnv

    env = VecEnv("pointmass", episodes)
    state, step = env.reset(jax.random.PRNGKey(seed)), jax.jit(env.step)
    returns, running = np.zeros(episodes), np.ones(episodes, bool)
    for _ in range(env.episode_length):
        state, outcome = step(state, policy(np.asarray(state.obs)))
        returns += np.where(running, np.asarray(outcome.reward), 0.0)
        running &= ~np.asarray(outcome.done)
    return returns


def parse_args(argv: list[str]) -> argparse.Namespace:
    """``--run-dir`` and ``--total-steps``; argparse exits with status 2 on a bad value."""
    parser = argparse.ArgumentParser(description="Train on pointmass from Python, then act with the policy.")
    parser.add_argument("--run-dir", default=None, help="a new or empty directory (default: a fresh one)")
    parser.add_argument("--total-steps", type=int, default=20_480, help="env steps to train (default 20480)")
    return parser.parse_args(argv)


if __name__ == "__main__":
    args = parse_args(sys.argv[1:])
    try:
        main(args.run_dir, args.total_steps)
    except coherent_jax.ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
