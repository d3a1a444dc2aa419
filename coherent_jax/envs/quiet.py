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

WARP_VAR = "COHERENT_JAX_MJX_WARP"  # 1: MJX imports its Warp engine (`quiet_imports`)


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
    """Imports MJX once, muted, and without its optional Warp backend unless `WARP_VAR` is 1.

    MJX imports NVIDIA Warp and its own Warp engine (``impl="warp"``, a GPU engine) whenever
    ``warp`` is installed, as MuJoCo Playground installs it; that is most of the time MJX takes
    to import (about half of a run's start-up before JAX compiles). This package steps MJX
    with ``impl="jax"`` only, so `quiet_imports`, called before anything imports MJX (Brax
    does), hides ``warp`` for the length of MJX's import: MJX then skips its Warp engine
    (and prints that it did, muted here). ``warp`` itself stays importable afterwards. A
    process that imported MJX before, or ``COHERENT_JAX_MJX_WARP=1``, keeps MJX's Warp engine.
    """
    if "mujoco.mjx" in sys.modules:
        return
    hide = "warp" not in sys.modules and os.environ.get(WARP_VAR) != "1"
    with quiet_stdio(force=True):
        if hide:
            sys.modules["warp"] = None  # an import of it raises ImportError
        try:
            import mujoco.mjx  # noqa: F401  # lazy: importing it so is this function's purpose
        finally:
            if hide and "warp" in sys.modules and sys.modules["warp"] is None:
                del sys.modules["warp"]
