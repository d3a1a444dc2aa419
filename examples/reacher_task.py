"""A task of your own: a 2-link planar arm reaching a target (``examples/tasks/reacher.xml``).

Train it with ``python -m coherent_jax.train env=examples/reacher_task.py:reacher`` from the
repository's root (from elsewhere, this file's path from there), or by module,
``env=examples.reacher_task:reacher``, with the root on PYTHONPATH; docs/tasks.md explains
the contract. Bodies of the model, as MuJoCo numbers them: 0 the world, 1 the upper arm, 2 the
forearm, 3 the fingertip, 4 the target. qpos = (shoulder, elbow, target x, target y).

* observation (10): cos and sin of the two joint angles, their velocities, the target's
  position and the fingertip's offset from it (x, y);
* reward: r = -|fingertip - target| - 0.01 |ctrl|^2 per step (0.05 s);
* termination: the fingertip is within 0.015 of the target (a success: no more cost);
* reset: joint angles uniform in [-pi, pi), at rest; the target uniform in angle at a
  distance in [0.05, 0.18) from the shoulder (the arm reaches 0.2);
* time limit: 50 steps (2.5 s).
"""

from pathlib import Path

import jax
import jax.numpy as jnp

from coherent_jax.envs import Kinematics, MjcfTask

MJCF = Path(__file__).resolve().parent / "tasks" / "reacher.xml"
FINGERTIP, TARGET = 3, 4
REACHED = 0.015


def _offset(k: Kinematics) -> jax.Array:
    """Fingertip minus target, (x, y)."""
    return k.xpos[FINGERTIP, :2] - k.xpos[TARGET, :2]


def observe(k: Kinematics) -> jax.Array:
    angles = k.qpos[:2]
    return jnp.concatenate([jnp.cos(angles), jnp.sin(angles), k.qvel[:2], k.qpos[2:4], _offset(k)])


def reward(before: Kinematics, after: Kinematics, ctrl: jax.Array, dt: float) -> jax.Array:
    return -jnp.linalg.norm(_offset(after)) - 0.01 * jnp.sum(jnp.square(ctrl))


def terminate(k: Kinematics) -> jax.Array:
    return jnp.linalg.norm(_offset(k)) < REACHED


def reset(key: jax.Array, init_q: jax.Array, nv: int) -> tuple[jax.Array, jax.Array]:
    k_arm, k_angle, k_radius = jax.random.split(key, 3)
    arm = jax.random.uniform(k_arm, (2,), minval=-jnp.pi, maxval=jnp.pi)
    angle = jax.random.uniform(k_angle, (), minval=-jnp.pi, maxval=jnp.pi)
    radius = jax.random.uniform(k_radius, (), minval=0.05, maxval=0.18)
    target = radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)])
    return init_q.at[:2].set(arm).at[2:4].set(target), jnp.zeros((nv,))


reacher = MjcfTask(
    mjcf=MJCF,
    fields=("xpos",),
    observe=observe,
    reward=reward,
    terminate=terminate,
    frame_skip=5,
    episode_length=50,
    reset_noise=reset,
)
