"""The one map from the agent's action in [-1, 1] to the action an environment receives.

Every policy of this package acts in [-1, 1]^p; `VecEnv.step` clips the action there and
the task maps it onto its own action space. Training (`coherent_jax.envs.mujoco_task.control`,
`coherent_jax.envs.brax_env`, a Gymnasium env's host pool in `coherent_jax.envs.host_gym`),
``evaluate engine=gymnasium`` and a shipped policy
(`coherent_jax.policy`) all map through this module, so the three cannot disagree:

    a_env = clip(a, -1, 1)                                  identity ([-1, 1] spaces)
    a_env = (high + low) / 2 + clip(a, -1, 1) (high - low) / 2   "centre" (Gymnasium's Box; eq. A)
    a_env = (clip(a, -1, 1) + 1) (high - low) / 2 + low          "brax" (Brax's own arithmetic; eq. B)

Eqs. A and B are the same affine map, rounded differently in float32; A is exactly
``a * high`` on a symmetric range. `ActionMap` is the map as data (kind, low, high), so it
can be stored with a policy, written into an exported graph, and built from a task
(`ActionMap.of_physics`) or from any Gymnasium ``Box`` (`ActionMap.of_box`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

KINDS = ("identity", "centre", "brax")


def to_bounds(action: Any, low: Any, high: Any) -> Any:
    """``action`` in [-1, 1] mapped affinely onto [low, high] as centre + a * half-width (eq. A,
    float32): exactly ``a * high`` on a symmetric range, the action Gymnasium's env receives,
    and ``a`` itself on [-1, 1]."""
    low, high = np.asarray(low, np.float32), np.asarray(high, np.float32)
    return (high + low) / 2 + action.astype(jnp.float32) * ((high - low) / 2)


def brax_bounds(action: Any, low: Any, high: Any) -> Any:
    """``action`` in [-1, 1] mapped onto [low, high] as Brax computes it (eq. B, float32)."""
    low, high = np.asarray(low, np.float32), np.asarray(high, np.float32)
    return (action.astype(jnp.float32) + 1.0) * (high - low) * 0.5 + low


class ActionMap(NamedTuple):
    """The map of one task: ``kind`` (one of `KINDS`) and the bounds ``low``, ``high`` [p]
    (float32 numpy) of the env's own action space."""

    kind: str
    low: np.ndarray
    high: np.ndarray

    @classmethod
    def make(cls, kind: str, low: Any, high: Any) -> ActionMap:
        if kind not in KINDS:
            raise ValueError(f"invalid action map kind {kind!r} (allowed: {', '.join(KINDS)})")
        low = np.asarray(low, np.float32).reshape(-1)
        high = np.asarray(high, np.float32).reshape(-1)
        if low.shape != high.shape or not np.all(np.isfinite(low) & np.isfinite(high) & (low <= high)):
            raise ValueError(
                f"invalid action bounds low={low.tolist()} high={high.tolist()} "
                "(allowed: finite, low <= high, the same size)"
            )
        return cls(kind, low, high)

    @classmethod
    def identity(cls, action_size: int) -> ActionMap:
        return cls.make("identity", -np.ones(action_size), np.ones(action_size))

    @classmethod
    def of_task(cls, scale_action: bool, brax_scaling: bool, ctrl_range: Any) -> ActionMap:
        """A MuJoCo task's map (`coherent_jax.envs.mujoco_task.NativeTask`'s ``scale_action`` and
        ``brax_scaling``) onto its actuators' ``ctrl_range`` [nu, 2]."""
        low, high = np.asarray(ctrl_range, np.float32).reshape(-1, 2).T
        if not scale_action:
            return cls.identity(low.shape[0])
        return cls.make("brax" if brax_scaling else "centre", low, high)

    @classmethod
    def of_box(cls, space: Any) -> ActionMap:
        """The map onto a Gymnasium ``Box`` (its ``low``, ``high``), Gymnasium's way (eq. A)."""
        return cls.make("centre", space.low, space.high)

    @classmethod
    def of_physics(cls, env: Any, action_size: int) -> ActionMap:
        """The map of a `coherent_jax.envs.vec_env.VecEnv`'s ``env``: a native/MJX task's
        (``spec``, ``ctrl_range``), a classic task's ([-max_action, max_action]), a
        Gymnasium env's (``gym:ID`` or a user's: its ``action_map``, the map onto its Box),
        else [-1, 1] (Brax's own envs act there)."""
        if isinstance(getattr(env, "action_map", None), ActionMap):
            return env.action_map
        spec, ctrl_range = getattr(env, "spec", None), getattr(env, "ctrl_range", None)
        if spec is not None and ctrl_range is not None and hasattr(spec, "scale_action"):
            return cls.of_task(spec.scale_action, spec.brax_scaling, ctrl_range)
        if hasattr(env, "max_action"):
            bound = np.full(action_size, env.max_action, np.float32)
            return cls.make("centre", -bound, bound)
        return cls.identity(action_size)

    def unclipped(self, action: Any) -> Any:
        """The map of an action already in [-1, 1] (what a task applies after `VecEnv.step`'s clip)."""
        if self.kind == "brax":
            return brax_bounds(action, self.low, self.high)
        if self.kind == "centre":
            return to_bounds(action, self.low, self.high)
        return action.astype(jnp.float32)

    def __call__(self, action: Any) -> Any:
        """The env's action for the agent's ``action`` [..., p]: clipped to [-1, 1], then mapped."""
        return self.unclipped(jnp.clip(action, -1.0, 1.0))

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "low": self.low.tolist(), "high": self.high.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ActionMap:
        return cls.make(d["kind"], d["low"], d["high"])
