"""Where a run's numbers came from, beside the package versions of ``versions.json``.

* ``git_commit``, ``git_dirty``: the commit of the checkout this package was imported
  from, and whether its tracked files differed from it. Untracked files do not count,
  nor do the results under `RESULTS_DATA` (experiments/results/): a suite updates its
  committed curves as each cell finishes, before they are committed, and that is data,
  not code. Both null outside a git checkout of the project (an installed wheel, no
  ``git``).
* ``cpu_model``: the processor's name (``model name`` of ``/proc/cpuinfo``, else
  `platform.processor`).
* ``cpu_vector_isa``: the widest vector extension the CPU reports (``avx512f``, ``avx2``,
  ``avx``, ``sse4_2``; null if none of these or unknown). XLA compiles for the host's
  extensions, so two machines at different levels can round float32 sums differently.

Everything here is best effort: a failure gives null, never an error.
"""

from __future__ import annotations

import platform
import subprocess
from pathlib import Path
from typing import Any

# Widest first: the first of these in the CPU's flags is its level.
VECTOR_LEVELS = ("avx512f", "avx2", "avx", "sse4_2")
PROJECT_ROOT = Path(__file__).resolve().parents[2]  # coherent_jax/run/provenance.py -> the checkout
#: tracked results data that `git_state` does not count as a change of the checkout
RESULTS_DATA = "experiments/results"


def _git(root: Path, *args: str) -> str | None:
    try:
        out = subprocess.run(
            ["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def git_state(root: Path = PROJECT_ROOT) -> dict[str, Any]:
    """``git_commit`` and ``git_dirty`` of the checkout at `root`; nulls if `root` is not one.

    A checkout that merely encloses `root` (a virtualenv inside another project) is not
    the project's: its top level must be `root` itself.
    """
    none = {"git_commit": None, "git_dirty": None}
    top = _git(root, "rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != Path(root).resolve():
        return none
    commit = _git(root, "rev-parse", "HEAD")
    code_only = ("--", ".", f":(exclude){RESULTS_DATA}")
    status = _git(root, "status", "--porcelain", "--untracked-files=no", *code_only)
    if commit is None or status is None:
        return none
    return {"git_commit": commit, "git_dirty": bool(status)}


def cpu_info(cpuinfo: Path = Path("/proc/cpuinfo")) -> dict[str, Any]:
    """``cpu_model`` and ``cpu_vector_isa`` from `cpuinfo` (Linux), else what `platform` says."""
    model, flags = None, set()
    try:
        for line in cpuinfo.read_text(errors="replace").splitlines():
            name, _, value = line.partition(":")
            name = name.strip()
            if name == "model name" and model is None:
                model = value.strip()
            elif name == "flags" and not flags:
                flags = set(value.split())
    except OSError:
        pass
    model = model or platform.processor() or None
    level = next((lvl for lvl in VECTOR_LEVELS if lvl in flags), None)
    return {"cpu_model": model, "cpu_vector_isa": level}


def provenance() -> dict[str, Any]:
    """The four fields of the module docstring."""
    return {**git_state(), **cpu_info()}
