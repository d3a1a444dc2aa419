"""A MuJoCo Playground environment of your choosing: a 3-link swimmer (docs/tasks.md, "Brax and
Playground environments").

Playground registers dm_control's swimmer with 6 links (``dmc-swimmer_swimmer6``); its
class takes the number of links, and a factory annotated to return an ``MjxEnv`` is all
``env=`` needs. Train it from the repository's root with

    python -m coherent_jax.train env=examples/train_playground_env.py:swimmer3 explore=coherent

or run this file, which trains PPO with coherent exploration at a small budget and
prints the evaluation returns. ``impl="jax"`` is plain MJX, which ``vmap``s (Playground
0.2.0 defaults to MJX's Warp implementation, which does not). The reward is dm_control's:
in [0, 1] per step, 1 with the nose within the target, falling off smoothly over 5 body
lengths; 1000-step episodes, no terminations.

Measured (this file, ``--total-steps 65536``: 16 envs x 128 steps x 32 iterations, seed 0,
one run, on 2 CPU cores shared with other work at a load of about 16, so the times are
loose): the evaluation return (4 episodes, deterministic policy) was 33.1, 265.9, 41.1
and 467.7 at 16k, 33k, 49k and 66k env steps; the program compiled in 761 s and trained
at 1332 env steps/s. ``python -m coherent_jax.evaluate RUN_DIR episodes=2 video=true``
on that run then gave 33.3 +- 3.2 (2 episodes of 1000 steps, other targets) and a
1000-frame video: the 467.7 was 4 episodes' luck with their targets as much as skill.
Short and noisy: it shows the env running through ``env=``, not a result about the
swimmer.
"""

from __future__ import annotations

import argparse
import time

from mujoco_playground import MjxEnv, dm_control_suite

import coherent_jax


def swimmer3() -> MjxEnv:
    """dm_control's swimmer with 3 links, on MJX's JAX implementation (``env=...:swimmer3``)."""
    return dm_control_suite.swimmer.Swim(n_links=3, config_overrides={"impl": "jax"})


def main(total_steps: int, seed: int) -> None:
    cfg = coherent_jax.make_config(
        env="examples/train_playground_env.py:swimmer3",
        explore="coherent",
        total_steps=total_steps,
        num_envs=16,
        unroll_length=128,
        eval_every=8,
        eval_episodes=4,
        seed=seed,
        progress=False,
    )
    start = time.time()
    result = coherent_jax.learn(cfg)
    for row in result.metrics:
        if row.get("eval/episode_return") is not None:
            print(f"{row['env_steps']:7d} env steps: eval return {row['eval/episode_return']:7.2f}")
    print(
        f"final eval return {result.summary['final_eval_return']:.2f} after {total_steps} env steps, "
        f"{time.time() - start:.0f} s; run in {result.run_dir}"
    )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--total-steps", type=int, default=65_536)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    main(args.total_steps, args.seed)
