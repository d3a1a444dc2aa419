"""Random-policy return and episode length of the standard tasks: ours against Gymnasium's.

    python experiments/random_policy_vs_gymnasium.py [halfcheetah hopper ...]

Ours: the first episode of each of 50 envs of `VecEnv` (native MuJoCo, the task's time
limit) under uniform random actions in [-1, 1], in one jitted scan. Gymnasium: 50
episodes of ``gym.make(id)`` (with its registered time limit) under uniform random
actions in its action space, seeds 1000..1049. Prints mean +- std of the returns and
the mean length; writes ``random_policy_vs_gymnasium.json``.
"""

import json
import os
import sys

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np

from coherent_jax.envs import VecEnv
from coherent_jax.envs.gym_v5 import SHORT_NAMES

EPISODES = 50


def ours(task: str) -> tuple[np.ndarray, np.ndarray]:
    """Returns and lengths of the first episode of each of EPISODES envs."""
    env = VecEnv(task, EPISODES)

    def run(key):
        def body(carry, k):
            state, ended, ret, length = carry
            action = jax.random.uniform(k, (EPISODES, env.action_size), minval=-1, maxval=1)
            state, out = env.step(state, action)
            ret = jnp.where(ended, ret, ret + out.reward)
            length = jnp.where(ended, length, length + 1)
            return (state, ended | out.done, ret, length), None

        init = (
            env.reset(key),
            jnp.zeros(EPISODES, bool),
            jnp.zeros(EPISODES),
            jnp.zeros(EPISODES, jnp.int32),
        )
        (_, ended, ret, length), _ = jax.lax.scan(body, init, jax.random.split(key, env.episode_length))
        return ended, ret, length

    ended, ret, length = jax.device_get(jax.jit(run)(jax.random.PRNGKey(0)))
    assert ended.all(), "every env ends an episode within the time limit"
    return ret, length


def gymnasium(gym_id: str) -> tuple[np.ndarray, np.ndarray]:
    env = gym.make(gym_id)
    env.action_space.seed(0)
    returns, lengths = [], []
    for episode in range(EPISODES):
        env.reset(seed=1000 + episode)
        total, steps, done = 0.0, 0, False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            total, steps, done = total + reward, steps + 1, terminated or truncated
        returns.append(total)
        lengths.append(steps)
    return np.array(returns), np.array(lengths)


def main(tasks: list[str]) -> None:
    result = {}
    for task in tasks or list(SHORT_NAMES):
        rows = {"ours": ours(task), "gymnasium": gymnasium(SHORT_NAMES[task])}
        result[task] = {k: [float(r.mean()), float(r.std()), float(n.mean())] for k, (r, n) in rows.items()}
        line = "   ".join(f"{k} {m:9.1f} +- {s:7.1f} (len {n:6.1f})" for k, (m, s, n) in result[task].items())
        print(f"{SHORT_NAMES[task]:<26} {line}", flush=True)
    print("load average", os.getloadavg())
    with open("random_policy_vs_gymnasium.json", "w") as f:
        json.dump(result, f, indent=1)


if __name__ == "__main__":
    main(sys.argv[1:])
