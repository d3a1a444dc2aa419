"""One silencer for the libraries that print on import or build (no JAX here).

A module of its own, importing only ``os`` and ``sys``, because its users sit on both sides
of JAX: the launch of a run imports it on the start-up path that loads no JAX
(`coherent_jax.run.launch`), and the modules that build envs with JAX, MuJoCo or Gymnasium
(`coherent_jax.envs.brax_env`, `coherent_jax.envs.gym_v5`, `coherent_jax.envs.gym_source`,
`coherent_jax.envs.user`, the evaluation) use it too; in any one of them, the launch would
load that module's dependencies.

Brax prints a line for its optional Warp backend on import, MJX for its missing
``warp`` backend, Warp its kernel-cache lines, and MuJoCo's compiler deprecation notes
(some from C, below Python's ``sys.stdout``): `quiet_stdio` points file descriptors 1
and 2 at ``/dev/null`` for the length of a ``with`` block.
"""

from __future__ import annotations

import os
import sys


class quiet_stdio:
    """Silences file descriptors 1 and 2 inside a ``with`` block.

    Without ``force`` it does nothing once ``brax.envs`` is imported (the import is
    what printed); ``force=True`` silences in any case.
    """

    def __init__(self, force: bool = False):
        self._force = force
        self._fds: tuple[int, int] | None = None

    def __enter__(self):
        if "brax.envs" in sys.modules and not self._force:
            self._fds = None
            return self
        sys.stdout.flush()
        sys.stderr.flush()
        self._devnull = os.open(os.devnull, os.O_WRONLY)
        self._fds = (os.dup(1), os.dup(2))
        os.dup2(self._devnull, 1)
        os.dup2(self._devnull, 2)
        return self

    def __exit__(self, *exc):
        if self._fds is not None:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(self._fds[0], 1)
            os.dup2(self._fds[1], 2)
            for fd in (*self._fds, self._devnull):
                os.close(fd)
        return False


def quiet_imports() -> None:
    """Imports MJX once with its output muted: it prints lines when its optional `warp` backend is missing."""
    with quiet_stdio(force=True):
        import mujoco.mjx  # noqa: F401  # lazy: importing it muted is this function's purpose
