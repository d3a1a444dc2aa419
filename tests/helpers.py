"""What the tests' subprocesses share: the environment they start with."""

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# The test run's compilation cache (made by conftest.pytest_configure), and the compile
# time from which a program is worth caching.
CACHE_VAR = "COHERENT_JAX_TEST_COMPILE_CACHE"
CACHE_MIN_COMPILE_S = 0.5


def child_env() -> dict[str, str]:
    """The environment of a test's subprocess: this one's, the project on PYTHONPATH, and
    the test run's compilation cache, so that a resumed run, a repeated command or a sweep
    after its single-run twin loads its programs instead of compiling them again.

    Loading a cached program logs a C++ warning per program ("Assume version
    compatibility", pjrt_executable.cc) on stderr, which the command-line tests read;
    TF_CPP_MIN_LOG_LEVEL=2 keeps C++ warnings off stderr (errors still show)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    if os.environ.get(CACHE_VAR):
        env["JAX_COMPILATION_CACHE_DIR"] = os.environ[CACHE_VAR]
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = str(CACHE_MIN_COMPILE_S)
        env["TF_CPP_MIN_LOG_LEVEL"] = "2"
    return env
