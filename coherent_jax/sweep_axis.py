"""A sweep's points axis: `vmap` over it, and conditions reduced over it to branch once.

A shared base apart from the sweep (`coherent_jax.run.sweep`, `coherent_jax.run.training`):
the envs, the strategies and the trainers, layers below `run/`, branch through it.

A sweep runs its grid points as one program, ``vmap(trainer.iteration, axis_name=
POINT_AXIS)``. Under `jax.vmap` a `jax.lax.cond` whose predicate may differ between
points becomes a select that computes *both* branches at every point: a fresh draw
of every env's episode noise, or a reset of every env, at every step. Reduced over
the points, the predicate is one value again and the cond computes one branch.

That is only right where either branch gives each point its own result, whichever
way the shared predicate falls: a branch that changes only the rows its own mask
selects (``jnp.where(first, fresh, held)``), or two branches that compute the same
values two ways. Outside a sweep (no axis of that name is bound) the predicate is
returned as it is.
"""

from __future__ import annotations

import jax

POINT_AXIS = "points"


def vmap_points(fn):
    """``fn`` vmapped over a sweep's leading point axis, named `POINT_AXIS`."""
    return jax.vmap(fn, axis_name=POINT_AXIS)


def any_point(pred: jax.Array) -> jax.Array:
    """``pred`` (a boolean scalar) true at any point of the sweep being traced."""
    try:
        return jax.lax.pmax(pred, POINT_AXIS)
    except NameError:  # not inside a sweep's vmap
        return pred


def least_point(value: jax.Array) -> jax.Array:
    """``value`` (a scalar) at its smallest over the sweep being traced."""
    try:
        return jax.lax.pmin(value, POINT_AXIS)
    except NameError:  # not inside a sweep's vmap
        return value


def all_points(pred: jax.Array) -> jax.Array:
    """``pred`` (a boolean scalar) true at every point of the sweep being traced: its least value."""
    return least_point(pred)
