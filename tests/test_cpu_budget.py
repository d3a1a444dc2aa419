"""The everyday subset's budget (tests/cpu_budget.py) fails a test over it that is not
marked slow, naming it and its CPU seconds, its subprocesses' included; nothing else."""

from cpu_budget import BUDGET_VAR

pytest_plugins = ["pytester"]

PROBES = """
import subprocess
import sys
import time

import pytest

BURN = "import time\\nt = time.process_time()\\nwhile time.process_time() - t < 0.2: pass"


def burn():
    exec(BURN)


def test_over_in_itself():
    burn()


def test_over_in_its_child():
    subprocess.run([sys.executable, "-c", BURN], check=True)


@pytest.mark.slow
def test_over_but_slow():
    burn()


def test_under():
    pass


def test_waits_without_cpu():
    time.sleep(0.2)
"""


def _outcomes(pytester, monkeypatch, budget):
    if budget is None:
        monkeypatch.delenv(BUDGET_VAR, raising=False)
    else:
        monkeypatch.setenv(BUDGET_VAR, budget)
    monkeypatch.setenv("PYTEST_DISABLE_PLUGIN_AUTOLOAD", "1")  # the installed plugins: seconds to load
    pytester.makepyfile(test_probes=PROBES)
    result = pytester.runpytest_inprocess("-p", "cpu_budget", "-p", "no:cacheprovider", "-rf", "-W", "ignore")
    reports = result.reprec.getreports("pytest_runtest_logreport")
    return {r.nodeid.split("::")[1]: r for r in reports if r.when == "call"}, result


def test_a_test_over_the_budget_without_the_slow_marker_fails_in_one_line(pytester, monkeypatch):
    calls, result = _outcomes(pytester, monkeypatch, "0.1")
    failed = {name for name, r in calls.items() if r.failed}
    assert failed == {"test_over_in_itself", "test_over_in_its_child"}, calls
    for name in failed:
        line = str(calls[name].longrepr)
        assert "\n" not in line and line.startswith("took "), line
        assert float(line.removeprefix("took ").split(" s of CPU")[0]) >= 0.2, line
        assert "over the everyday subset's 0.1 s" in line, line
        assert line.endswith(f"mark test_probes.py::{name} @pytest.mark.slow or make it faster"), line
    result.stdout.fnmatch_lines(["FAILED test_probes.py::test_over_in_itself - took 0.* s of CPU*"])


def test_the_budget_is_enforced_only_when_set(pytester, monkeypatch):
    calls, _ = _outcomes(pytester, monkeypatch, None)
    assert all(r.passed for r in calls.values()) and len(calls) == 5, calls


def test_each_test_carries_its_cpu_seconds_into_the_junit_report(pytester, monkeypatch):
    """Budget or not, a JUnit report gives each test's CPU seconds (a child's included)."""
    calls, _ = _outcomes(pytester, monkeypatch, None)
    cpu = {name: dict(r.user_properties)["cpu_s"] for name, r in calls.items()}
    assert cpu["test_over_in_itself"] >= 0.2 and cpu["test_over_in_its_child"] >= 0.2, cpu
    assert cpu["test_under"] < 0.1 and cpu["test_waits_without_cpu"] < 0.1, cpu
