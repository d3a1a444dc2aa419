"""What ends a run early: SIGINT/SIGTERM, a request to stop after the current iteration
(`StopRequest`), and a divergence (`DivergenceError`, raised by `coherent_jax.run.divergence`)."""

from __future__ import annotations

import signal
import sys
import threading
from typing import Any

from coherent_jax.run.runs import PREFIX


class DivergenceError(RuntimeError):
    """A loss or a parameter became non-finite; the message names the iteration and the quantity."""


class StopRequest:
    """Turns SIGINT/SIGTERM into a request to stop after the current iteration.

    Installed before anything slow (imports, compiles), so a Ctrl-C at any moment
    ends the program cleanly instead of with a traceback. A second signal ends the
    process at once, by the signal's default action.
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}

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
