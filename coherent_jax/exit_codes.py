"""The exit statuses of every command, in one place.

It stands alone, small, because every command (and its JAX-free start-up) imports it
and it imports nothing of the package: a shared base of the layering.

* 0: done (also: a resumed run that was already complete);
* `EXIT_ENV_FAILED` (1): a task's own env raised mid-run (a Gymnasium env's ``step``);
  the last checkpoint is kept and ``resume=`` continues once the env is fixed;
* `EXIT_BAD_INPUT` (2): bad input, refused in one line before anything is written;
* `EXIT_DIVERGED` (3): a loss or a parameter became non-finite (a run), or a grid
  point did (a sweep, at its end);
* `EXIT_PEER_FAILED` (4): another process of a ``distributed=true`` run failed
  (resumable; `coherent_jax.run.multihost`);
* 128 + signal number (`signal_status`): stopped by SIGINT/SIGTERM (resumable), the
  shell's convention for a process ended by a signal.
"""

from __future__ import annotations

EXIT_OK = 0
EXIT_ENV_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 3
EXIT_PEER_FAILED = 4


def signal_status(signum: int) -> int:
    """The exit status of a command stopped by signal `signum`: 128 + its number."""
    return 128 + int(signum)
