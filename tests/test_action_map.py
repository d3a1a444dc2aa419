"""The one action map (`coherent_jax.envs.action_map`): tasks with non-unit bounds, Gymnasium's
Box, and Brax's arithmetic, against float64 references and against Gymnasium's own spaces."""

from __future__ import annotations

import gymnasium
import jax.numpy as jnp
import numpy as np
import pytest

from coherent_jax.envs.action_map import ActionMap
from coherent_jax.envs.physics import NATIVE_TASKS
from coherent_jax.envs.vec_env import VecEnv
from coherent_jax.run.evaluation import gymnasium_action_map

A = np.linspace(-1.5, 1.5, 13, dtype=np.float32)  # beyond [-1, 1] too: the map clips first


@pytest.mark.parametrize(
    ("task", "gym_id", "bound"),
    [("inverted_pendulum", "InvertedPendulum-v5", 3.0), ("humanoid", "Humanoid-v5", 0.4)],
)
def test_non_unit_bounds_of_builtin_tasks(task, gym_id, bound):
    env = VecEnv(task, 1, None, "native", 1)
    amap = ActionMap.of_physics(env.env, env.action_size)
    space = gymnasium.make(gym_id).action_space
    assert amap.kind == "centre"
    np.testing.assert_array_equal(amap.low, np.float32(space.low))
    np.testing.assert_array_equal(amap.high, np.float32(space.high))
    np.testing.assert_allclose(amap.high, bound, rtol=1e-6)
    a = np.tile(A[:, None], (1, env.action_size))
    want = np.clip(a.astype(np.float64), -1, 1) * np.float64(space.high)  # symmetric: a * high
    np.testing.assert_allclose(np.asarray(amap(jnp.asarray(a))), want, rtol=1e-6, atol=1e-7)
    # evaluate engine=gymnasium maps through the same map
    assert gymnasium_action_map(task, space).to_dict() == amap.to_dict()


def test_box_and_brax_arithmetic_against_float64():
    low, high = np.array([-2.0, 0.0, 1.0]), np.array([1.0, 0.5, 3.0])
    box = gymnasium.spaces.Box(low.astype(np.float32), high.astype(np.float32))
    a = np.stack([A[:3], A[5:8], A[-3:]], axis=-1)
    want = low + (np.clip(a.astype(np.float64), -1, 1) + 1) * (high - low) / 2
    for amap in (ActionMap.of_box(box), ActionMap.make("brax", low, high)):
        np.testing.assert_allclose(np.asarray(amap(jnp.asarray(a))), want, rtol=1e-6, atol=1e-6)
    ident = ActionMap.identity(3)
    np.testing.assert_array_equal(np.asarray(ident(jnp.asarray(a))), np.clip(a, -1, 1))
    assert ActionMap.from_dict(ActionMap.of_box(box).to_dict()).to_dict() == ActionMap.of_box(box).to_dict()


def test_training_control_is_the_map():
    """A Brax-scaled native task (`brax-inverted_pendulum`-style) and a Gymnasium one use it."""
    for name, task in NATIVE_TASKS.items():
        if task.scale_action:
            amap = ActionMap.of_task(True, task.brax_scaling, np.array([[-3.0, 3.0]]))
            assert amap.kind == ("brax" if task.brax_scaling else "centre"), name


def test_bad_bounds_and_kind_in_one_line():
    with pytest.raises(ValueError, match="allowed: identity, centre, brax"):
        ActionMap.make("tanh", [-1], [1])
    with pytest.raises(ValueError, match="allowed: finite"):
        ActionMap.make("centre", [1.0], [-1.0])
