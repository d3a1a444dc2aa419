"""A checkpoint's train state as bytes (`state_to_bytes`) and back (`restore_state`); the rest of
the checkpoint record is `coherent_jax.run.runs`'s."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import serialization

from coherent_jax.run.collective import to_host
from coherent_jax.run.runs import CheckpointError


def state_to_bytes(state: Any) -> bytes:
    """The leaves of the state pytree, in tree order, as flax msgpack.

    A state spread over several processes is gathered first: every process must call this.

    Leaves rather than the tree itself: the physics state of an MJX environment is a
    pytree that flax's serialisation does not know, and the tree structure is
    rebuilt from the trainer's own template on restore.
    """
    leaves = jax.tree_util.tree_leaves(to_host(state))
    return serialization.msgpack_serialize({str(i): np.asarray(x) for i, x in enumerate(leaves)})


def restore_state(template: Any, state_bytes: bytes, path: Path) -> Any:
    """The state pytree of a checkpoint, shaped like `template` (checked leaf by leaf).

    `template` may hold arrays or ``jax.ShapeDtypeStruct``s (``jax.eval_shape`` of
    the trainer's ``init``).
    """
    try:
        stored = serialization.msgpack_restore(state_bytes)
        leaves = [np.asarray(stored[str(i)]) for i in range(len(stored))]
    except Exception as exc:  # noqa: BLE001
        raise CheckpointError(f"checkpoint {str(path)!r}: unreadable state ({exc})") from None
    flat_t, treedef = jax.tree_util.tree_flatten_with_path(template)
    if len(flat_t) != len(leaves):
        raise CheckpointError(
            f"checkpoint {str(path)!r} has {len(leaves)} arrays, this trainer {len(flat_t)}"
        )
    for (where, t), s in zip(flat_t, leaves, strict=True):
        if s.shape != tuple(t.shape) or s.dtype != t.dtype:
            raise CheckpointError(
                f"checkpoint {str(path)!r}: {jax.tree_util.keystr(where)} is {s.dtype}{list(s.shape)}, "
                f"this trainer expects {t.dtype}{list(t.shape)}"
            )
    return jax.device_put(jax.tree_util.tree_unflatten(treedef, leaves))
