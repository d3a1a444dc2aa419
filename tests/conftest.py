"""Every test leaves the process as it found it.

A training run's result depends on process-wide state besides its seed: JAX's config
(float64, matmul precision, PRNG implementation), the config defaults, the task tables
and the environment variables. A test that changes one and does not restore it makes
later tests in the same worker train differently, a failure that shows only in the
full suite and points at the wrong test. This guard names the test that leaked.
"""

import copy
import os
import shutil
import tempfile

import cpu_budget
import jax
import pytest
import schedule
from helpers import CACHE_MIN_COMPILE_S
from helpers import CACHE_VAR as _CACHE_VAR
from references import x64_enabled

from coherent_jax.config import parse_overrides
from coherent_jax.envs import physics


def pytest_configure(config):
    """A compilation cache for this test run only: many tests compile the same program
    again (a run and its resume, the same seed twice, a sweep point and its single run),
    and XLA's compiles are most of the suite's time. The controller makes the directory;
    xdist's workers inherit it through the environment, and the tests' subprocesses
    through `helpers.child_env`. Registers `cpu_budget`, the everyday subset's budget."""
    config.pluginmanager.register(cpu_budget, "cpu_budget")
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ[_CACHE_VAR] = tempfile.mkdtemp(prefix="coherent_jax_test_compile_cache_")
    cache = os.environ[_CACHE_VAR]
    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_S)


def pytest_collection_modifyitems(session, config, items):
    """Longest tests first (`schedule`), so that the two workers of ``-n 2`` end together."""
    items[:] = schedule.longest_first(items, schedule.read_durations())


def pytest_unconfigure(config):
    if not os.environ.get("PYTEST_XDIST_WORKER"):  # the controller, after every worker ended
        shutil.rmtree(os.environ.get(_CACHE_VAR, ""), ignore_errors=True)


# Environment variables that change what a run computes or how fast: JAX's and XLA's
# settings, the thread pools', the project's own. (Libraries set others on import, such
# as CRC32C_SW_MODE; the renderer's MUJOCO_GL is set by `evaluate` on purpose.)
_RELEVANT_ENV = ("JAX_", "XLA_", "COHERENT_", "OPENBLAS_", "OMP_", "MKL_", "TF_")


def _snapshot() -> dict:
    return {
        "jax config": {name: getattr(jax.config, name, None) for name in sorted(jax.config.values)},
        "config defaults": repr(parse_overrides([])),
        "native tasks": repr(physics.NATIVE_TASKS),
        "environment": {k: v for k, v in os.environ.items() if k.startswith(_RELEVANT_ENV)},
    }


def _differences(before: dict, after: dict) -> list[str]:
    out = []
    for part, old in before.items():
        new = after[part]
        if isinstance(old, dict):
            for key in sorted(set(old) | set(new)):
                if old.get(key) != new.get(key):
                    out.append(f"{part}: {key} {old.get(key)!r} -> {new.get(key)!r}")
        elif old != new:
            out.append(f"{part} changed")
    return out


@pytest.fixture(autouse=True)
def leaves_global_state_as_found():
    """Fails the test that changed process-wide state without restoring it."""
    before = copy.deepcopy(_snapshot())
    yield
    changed = _differences(before, _snapshot())
    assert not changed, "test left process-wide state changed: " + "; ".join(changed)


@pytest.fixture
def x64():
    """Runs the test with jax_enable_x64 on (the float64 references), restored after it."""
    with x64_enabled():
        yield
