"""The everyday subset's budget: a test without the `slow` marker whose call takes more
than COHERENT_JAX_TEST_BUDGET_S seconds fails, in one line naming it and its time.

The time is CPU seconds, not wall seconds: the test process's own (every thread, XLA's
compiler and its thread pool included) plus that of the subprocesses it waited for (a
command-line test's child). Wall time grows with whatever else the machine runs (the
other xdist worker, other jobs on a shared runner), so a wall-time budget fails tests
that did nothing wrong; a test's CPU seconds hardly move with the load. On CI's 2-core
machine with the suite's two workers, a single-threaded test's CPU seconds are its wall
seconds.

Enforced only when COHERENT_JAX_TEST_BUDGET_S is set: a test's CPU seconds still depend on
the CPU, so a slower laptop, a debugger or a coverage run would fail tests that fit CI's
budget. `.ci/run` does not set it yet (docs/development.md: two parametrisations of the
everyday subset still take 20-34 s of CPU, as the first of their parametrisations
compiles the programs the others reuse). Unset, the durations table (pyproject's addopts) still
shows the slowest tests.
"""

import os
import resource

import pytest

BUDGET_VAR = "COHERENT_JAX_TEST_BUDGET_S"
_SPENT = pytest.StashKey[float]()
_BUDGET = pytest.StashKey[float | None]()


def cpu_seconds() -> float:
    """User and system CPU seconds of this process and of its waited-for children."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def over_budget(nodeid: str, spent: float, budget: float) -> str:
    """The failure's one line (its start is what the short summary shows after the test's name)."""
    return (
        f"took {spent:.1f} s of CPU, over the everyday subset's {budget:g} s ({BUDGET_VAR}): "
        f"mark {nodeid} @pytest.mark.slow or make it faster"
    )


def pytest_configure(config):
    """The budget is the session's, read once: a test that sets the variable for a nested
    session leaves its own budget alone."""
    budget = os.environ.get(BUDGET_VAR)
    config.stash[_BUDGET] = float(budget) if budget else None


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item):
    start = cpu_seconds()
    try:
        return (yield)
    finally:
        item.stash[_SPENT] = cpu_seconds() - start
        # In a JUnit report (--junitxml) each test carries its CPU seconds, which the
        # budget is checked against (wall seconds are its "time").
        item.user_properties.append(("cpu_s", round(item.stash[_SPENT], 2)))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    report = yield
    budget = item.config.stash[_BUDGET]
    if call.when != "call" or not report.passed or budget is None or item.get_closest_marker("slow"):
        return report
    spent = item.stash.get(_SPENT, 0.0)
    if spent > budget:
        report.outcome = "failed"
        report.longrepr = over_budget(item.nodeid, spent, budget)
    return report
