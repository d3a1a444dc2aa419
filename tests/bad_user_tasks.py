"""Broken variants of the example task (``examples/reacher_task.py``), one problem each, for
``tests/test_user_task.py``: ``env=bad_user_tasks:NAME`` must be refused naming the problem."""

import dataclasses
import tempfile
from pathlib import Path

import jax.numpy as jnp

from coherent_jax.envs import MjcfTask
from examples.reacher_task import reacher

not_a_task = 3
unknown_field = dataclasses.replace(reacher, fields=("xpos", "qacc"))
missing_mjcf = dataclasses.replace(reacher, mjcf=Path(__file__).parent / "no_such_model.xml")
obs_matrix = dataclasses.replace(reacher, observe=lambda k: k.xpos)
obs_nan = dataclasses.replace(reacher, observe=lambda k: jnp.log(-1.0 - jnp.abs(k.qpos)))
obs_reads_unnamed_field = dataclasses.replace(reacher, fields=(), observe=lambda k: k.xpos[3])
reward_vector = dataclasses.replace(reacher, reward=lambda k0, k1, ctrl, dt: -jnp.square(ctrl))
reward_nan = dataclasses.replace(reacher, reward=lambda k0, k1, ctrl, dt: jnp.nan * k1.qpos[0])
terminate_half = dataclasses.replace(reacher, terminate=lambda k: 0.5 + 0.0 * k.qpos[0])
reset_short = dataclasses.replace(reacher, reset_noise=lambda key, q, nv: (q[:2], jnp.zeros(nv)))
terminate_vector = dataclasses.replace(reacher, terminate=lambda k: k.qpos > 10.0)


def invalid_mjcf() -> MjcfTask:
    """A task whose MJCF is not a model MuJoCo compiles (a function returning the task)."""
    path = Path(tempfile.mkdtemp()) / "broken.xml"
    path.write_text("<mujoco><worldbody><body><joint type='wobbly'/></body></worldbody></mujoco>")
    return dataclasses.replace(reacher, mjcf=path)


def raises() -> MjcfTask:
    raise RuntimeError("the definition failed")


def unannotated():
    """A function that would make a task but does not say so: refused without being called."""
    raise RuntimeError("called although not declared to make a task")
