"""What ends a run early: SIGINT/SIGTERM or a callback, a request to stop after the current
iteration (`StopRequest`), and a divergence (`DivergenceError`, raised by
`coherent_jax.run.divergence`)."""

from __future__ import annotations

import signal
import sys
import threading
from typing import Any

from coherent_jax.run.runs import PREFIX


class DivergenceError(RuntimeError):
    """A loss or a parameter became non-finite; the message names the iteration and the quantity."""


CALLBACK = "callback"  # a summary's ``stopped_by`` when a callback stopped the run


class StopRequest:
    """Turns SIGINT/SIGTERM, or a callback's `request`, into a request to stop after the
    current iteration.

    Installed before anything slow (imports, compiles), so a Ctrl-C at any moment
    ends the program cleanly instead of with a traceback. A second signal ends the
    process at once, by the signal's default action. ``signum`` is the signal's number;
    ``reason`` what a callback said (`coherent_jax.run.callbacks`).
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self.reason: str | None = None
        self._previous: dict[int, Any] = {}

    def request(self, reason: str) -> None:
        """A callback's request to stop after the current iteration (the first reason is kept)."""
        if self.reason is None:
            self.reason = reason

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is not None:
            signal.signal(signum, signal.SIG_DFL)
            signal.raise_signal(signum)
            return
        self.signum = signum
        print(
            f"\n{PREFIX} {signal.Signals(signum).name}: stopping after the current step",
            file=sys.stderr,
            flush=True,
        )

    @property
    def name(self) -> str | None:
        return signal.Signals(self.signum).name if self.signum is not None else None

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
