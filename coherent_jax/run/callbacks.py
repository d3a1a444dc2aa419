"""Callbacks: user code the training loop calls, to watch a run, log it elsewhere or stop it.

    class StopAt(coherent_jax.Callback):
        def on_evaluation(self, row):
            self.best = row["eval/episode_return"]

        def on_iteration(self, row):
            return row.get("eval/episode_return", -inf) >= 100.0   # True: stop here

    coherent_jax.learn(cfg, callbacks=[StopAt()])

A callback is any object with an ``on_iteration`` method (`CallbackLike`); ``on_start``,
``on_evaluation`` and ``on_end`` are called where it has them. `Callback` is a base class with
all four, every one a no-op by default:

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
from typing import Any, NamedTuple, Protocol, runtime_checkable

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


@runtime_checkable
class CallbackLike(Protocol):
    """What the loop calls: any object with ``on_iteration``; ``on_start``, ``on_evaluation`` and
    ``on_end`` are optional (called where the object has them). `Callback` is one."""

    def on_iteration(self, row: dict[str, Any]) -> bool | Stop | None: ...


HOOKS = ("on_start", "on_iteration", "on_evaluation", "on_end")
_ALLOWED = "allowed: objects with an on_iteration method, e.g. coherent_jax.Callback subclasses"


def _problem(cb: Any) -> str | None:
    """Why `cb` is not a callback (one line), or None."""
    if isinstance(cb, type):
        return f"the class {cb.__name__}, not an instance of it ({cb.__name__}())"
    if not isinstance(cb, CallbackLike):
        return f"a {type(cb).__name__} without an on_iteration method"
    not_callable = [h for h in HOOKS if hasattr(cb, h) and not callable(getattr(cb, h))]
    return f"a {type(cb).__name__} whose {', '.join(not_callable)} is not a method" if not_callable else None


def checked(callbacks: Iterable[Any] | None) -> tuple[CallbackLike, ...]:
    """`callbacks` as a tuple; anything but a list of objects with ``on_iteration`` (and hooks that
    are methods) is a `ConfigError` naming the object and what it lacks."""
    if callbacks is None:
        return ()
    if isinstance(callbacks, (CallbackLike, str)) or not isinstance(callbacks, Iterable):
        raise ConfigError(f"invalid callbacks {callbacks!r} (allowed: a list of callbacks; {_ALLOWED})")
    found = tuple(callbacks)
    for cb in found:
        problem = _problem(cb)
        if problem:
            raise ConfigError(f"invalid callback {cb!r}: {problem} ({_ALLOWED})")
    return found


def start(callbacks: Sequence[CallbackLike], info: StartInfo) -> None:
    """``on_start`` of each callback that has it."""
    for cb in callbacks:
        hook = getattr(cb, "on_start", None)  # optional
        if hook is not None:
            hook(info)


def iteration(callbacks: Sequence[CallbackLike], row: dict[str, Any]) -> str | None:
    """``on_evaluation`` (on an evaluation row, where a callback has it) and ``on_iteration`` of
    each callback; the reason to stop of the first that asked to (None: go on)."""
    evaluated = any(k.startswith("eval/") for k in row)
    reasons = []
    for cb in callbacks:
        on_evaluation = getattr(cb, "on_evaluation", None)  # optional
        if evaluated and on_evaluation is not None:
            on_evaluation(dict(row))
        answer = cb.on_iteration(dict(row))  # each its own copy: one callback cannot change another's row
        if isinstance(answer, Stop):
            reasons.append(answer.reason)
        elif answer is not None and bool(answer):
            reasons.append(f"{type(cb).__name__}.on_iteration returned {answer!r}")
    return reasons[0] if reasons else None


def end(callbacks: Sequence[CallbackLike], summary: dict[str, Any]) -> None:
    """``on_end`` of each callback that has it."""
    for cb in callbacks:
        hook = getattr(cb, "on_end", None)  # optional
        if hook is not None:
            hook(summary)
