"""Callbacks: user code the training loop calls, to watch a run, log it elsewhere or stop it.

    class StopAt(coherent_jax.Callback):
        def on_evaluation(self, row):
            self.best = row["eval/episode_return"]

        def on_iteration(self, row):
            return row.get("eval/episode_return", -inf) >= 100.0   # True: stop here

    coherent_jax.learn(cfg, callbacks=[StopAt()])

A `Callback`'s hooks, every one a no-op by default:

* ``on_start(info)``: once, before the first iteration, with a `StartInfo` (the config, the run
  directory, the iteration the run starts after: 0, or a resumed checkpoint's);
* ``on_evaluation(row)``: on the rows that hold an evaluation (``eval/*`` keys), before
  ``on_iteration`` of the same row;
* ``on_iteration(row) -> bool | Stop | None``: after every iteration, with its row exactly as
  ``metrics.jsonl`` holds it (``iteration``, ``env_steps``, ``time_s``, ``train/*``, ``eval/*``
  on evaluation rows; None where a value was not finite). A true value or a `Stop` stops training
  after this iteration, as SIGINT/SIGTERM do: a checkpoint is written, the summary's
  ``stopped_by`` is ``"callback"`` and its ``stop_reason`` says why, and ``resume=`` continues
  from there as if the run had not stopped;
* ``on_end(summary)``: once, with the summary (also when a signal or a callback stopped the
  run; not when it raised, e.g. on a divergence).

Every callback sees every row, in the order given, even after an earlier one asked to stop.
The functions below are what the loop calls; they run in the host loop, between compiled
iterations, so a callback cannot change what the iteration computes: a run with callbacks
that do not stop it is bit-identical to one without.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from coherent_jax.config import Config, ConfigError


class StartInfo(NamedTuple):
    """What ``on_start`` receives: the run's config, its directory (None: no directory, a run
    called with none) and the iteration it starts after (0 for a new run)."""

    config: Config
    run_dir: Path | None
    start_iteration: int


class Stop(NamedTuple):
    """What ``on_iteration`` returns to stop training, with the reason the summary records."""

    reason: str = "a callback asked to stop"


class Callback:
    """The base of a user's callback: override the hooks you need (see the module's docstring)."""

    def on_start(self, info: StartInfo) -> None:
        """Once, before the first iteration."""

    def on_iteration(self, row: dict[str, Any]) -> bool | Stop | None:
        """After every iteration; True or a `Stop` stops training after it."""
        return None

    def on_evaluation(self, row: dict[str, Any]) -> None:
        """On each row that holds an evaluation (``eval/*``)."""

    def on_end(self, summary: dict[str, Any]) -> None:
        """Once, with the run's summary."""


def checked(callbacks: Iterable[Any] | None) -> tuple[Callback, ...]:
    """`callbacks` as a tuple; anything but `Callback` instances is a `ConfigError` naming it."""
    if callbacks is None:
        return ()
    if isinstance(callbacks, Callback) or not isinstance(callbacks, Iterable):
        raise ConfigError(
            f"invalid callbacks {callbacks!r} (allowed: a list of coherent_jax.Callback instances)"
        )
    found = tuple(callbacks)
    for cb in found:
        if not isinstance(cb, Callback):
            raise ConfigError(
                f"invalid callback {cb!r}: a {type(cb).__name__} "
                "(allowed: instances of coherent_jax.Callback subclasses)"
            )
    return found


def start(callbacks: Sequence[Callback], info: StartInfo) -> None:
    """``on_start`` of each callback."""
    for cb in callbacks:
        cb.on_start(info)


def iteration(callbacks: Sequence[Callback], row: dict[str, Any]) -> str | None:
    """``on_evaluation`` (on an evaluation row) and ``on_iteration`` of each callback; the
    reason to stop of the first that asked to (None: go on)."""
    evaluated = any(k.startswith("eval/") for k in row)
    reasons = []
    for cb in callbacks:
        if evaluated:
            cb.on_evaluation(dict(row))
        answer = cb.on_iteration(dict(row))  # each its own copy: one callback cannot change another's row
        if isinstance(answer, Stop):
            reasons.append(answer.reason)
        elif answer is not None and bool(answer):
            reasons.append(f"{type(cb).__name__}.on_iteration returned {answer!r}")
    return reasons[0] if reasons else None


def end(callbacks: Sequence[Callback], summary: dict[str, Any]) -> None:
    """``on_end`` of each callback."""
    for cb in callbacks:
        cb.on_end(summary)
