"""Train from Python, read the run, and act with its policy (docs/api.md).

    python examples/train_and_act.py [RUN_DIR]

Trains PPO with coherent exploration on ``pointmass`` (the analytic test task, which
compiles fastest), prints the evaluation returns the run logged, then loads the policy
back from the run directory and steps the task with it from Python, one numpy
observation batch at a time: the deterministic episodes an evaluation runs.
"""

from __future__ import annotations

import sys

import numpy as np

import coherent_jax


def main(run_dir: str = "runs/example-pointmass") -> None:
    cfg = coherent_jax.Config.from_overrides(
        env="pointmass",
        explore="coherent",
        total_steps=20_480,  # 10 iterations of 32 envs x 64 steps
        num_envs=32,
        eval_every=2,
        run_dir=run_dir,
        progress=False,
        **{"coherent.beta": 0.1},
    )
    result = coherent_jax.train(cfg)
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


if __name__ == "__main__":
    main(*sys.argv[1:2])
