"""A Gymnasium env of your own, unregistered, trained as it is: a point on a line reaching a target.

Train it from the repository's root with

    python -m coherent_jax.train env=examples/train_gym_env.py:TargetLine episode_length=50 \\
        total_steps=100000 num_envs=16

or run this file (``python examples/train_gym_env.py``), which does the same through the
Python API, `coherent_jax.learn`. The env is stepped on the host from inside the compiled
training iteration (docs/tasks.md, "Bring your own environment").

* observation (2): the point's position x and the target t, both in [-1, 1];
* action (1): a velocity in [-1, 1]; x <- clip(x + 0.1 a, -1, 1);
* reward: r = -|x - t| per step after the move;
* reset: x and t uniform in [-1, 1); no termination, the run's time limit ends episodes.

The optimum moves straight to the target at full speed (at most 20 steps) and stays there:
a 50-step episode then returns -sum_k max(|x0 - t| - 0.1 k, 0), -3.0 on average; a policy
that does not move returns -50 E|x0 - t| = -33.
"""

import gymnasium
import numpy as np
from gymnasium import spaces


class TargetLine(gymnasium.Env):
    """A point on [-1, 1] steered by its velocity to a target drawn at each reset."""

    observation_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.target = self.np_random.uniform(-1.0, 1.0, 2)
        return self._obs(), {}

    def step(self, action):
        self.x = float(np.clip(self.x + 0.1 * float(action[0]), -1.0, 1.0))
        reward = -abs(self.x - self.target)
        return self._obs(), reward, False, False, {}

    def _obs(self):
        return np.array([self.x, self.target], np.float32)


if __name__ == "__main__":
    import coherent_jax

    result = coherent_jax.learn(
        {
            "env": "examples/train_gym_env.py:TargetLine",
            "episode_length": 50,
            "total_steps": 100_000,
            "num_envs": 16,
        }
    )
    print(result)
