"""A sweep's grid (`SweepPlan`) and its points (`Point`), as `coherent_jax.sweep` parses them."""

from __future__ import annotations

import dataclasses
from typing import Any

from coherent_jax.config import Config
from coherent_jax.sweeps.table import fmt


@dataclasses.dataclass(frozen=True)
class Point:
    """One grid point: its settings along the non-seed axes, its seed and its config."""

    index: int
    values: dict[str, Any]
    seed: int
    cfg: Config

    @property
    def name(self) -> str:
        # A group's key by its last part (``beta=0.1``): the names sweeps have always had.
        parts = [f"{k.rsplit('.', 1)[-1]}={fmt(v)}" for k, v in self.values.items()]
        return "-".join([f"p{self.index:03d}", *parts, f"seed={self.seed}"])


@dataclasses.dataclass(frozen=True)
class SweepPlan:
    """The validated grid: the shared config, the axes in the order given, the seeds, the points."""

    base: Config
    axes: dict[str, list[Any]]
    seeds: list[int]
    points: list[Point]
