"""The divergence guard's checks: a non-finite loss or parameter stops a run.

After every iteration the loop (`coherent_jax.run.loop.guard`) checks each live point:
a loss metric of an iteration that applied an update, and every parameter, must be
finite. A single run stops with `DivergenceError`, naming the iteration, the
quantity and the last good checkpoint; a sweep marks the point and continues.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import jax
import numpy as np

from coherent_jax.agents.trainer import Trainer
from coherent_jax.run.runs import CHECKPOINT
from coherent_jax.run.stop import DivergenceError


class PointView:
    """One point of a stacked state, for `check_finite`'s parameter search."""

    def __init__(self, trainer: Trainer, index: int) -> None:
        self.trainer, self.index = trainer, index

    def export_params(self, states: Any) -> Any:
        return jax.tree.map(lambda x: x[self.index], self.trainer.export_params(states))


def first_non_finite(tree: Any) -> str:
    """Path of the first array of `tree` (on the host) holding a NaN or an infinity."""
    for where, leaf in jax.tree_util.tree_flatten_with_path(jax.device_get(tree))[0]:
        leaf = np.asarray(leaf)
        if np.issubdtype(leaf.dtype, np.inexact) and not np.all(np.isfinite(leaf)):
            return jax.tree_util.keystr(where)
    return "?"


def check_finite(
    it: int,
    metrics: dict[str, float],
    params_ok: bool,
    state: Any,
    trainer: Trainer | PointView,
    run_dir: Path | None,
    saved: int,
) -> None:
    """Raises `DivergenceError` if a loss metric or a parameter is non-finite.

    Losses are checked only when the iteration applied an update
    (``train/updates_applied`` > 0, or absent): SAC reports NaN losses by design while
    its replay buffer warms up. Parameters are always checked. `saved` is the
    iteration of the last checkpoint written (the one a resume starts from).
    """
    updated = metrics.get("train/updates_applied", 1.0) > 0
    bad = [k for k, v in metrics.items() if updated and "loss" in k and not math.isfinite(v)]
    if not bad and params_ok:
        return
    if bad:
        quantity = f"{bad[0]} = {metrics[bad[0]]}"
    else:
        quantity = f"parameter {first_non_finite(trainer.export_params(state))} is not finite"
    kept = (
        f"; last good checkpoint: iteration {saved} in {run_dir / CHECKPOINT}"
        if run_dir and (run_dir / CHECKPOINT).exists()
        else "; no checkpoint was written before it"
    )
    raise DivergenceError(f"diverged at iteration {it}: {quantity}{kept}")
