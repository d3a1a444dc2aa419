"""The order the suite's tests start in: longest first, so that ``pytest -n 2`` ends together.

xdist's ``load`` scheduling hands each worker the next test in collection order as it frees
up. In file order, one long test collected late (a study's documentation run takes minutes)
starts when the other worker has nearly finished and runs alone to the end: the suite's
wall time is then the sum of its tail, not half its total. Started longest first, the
short tests fill the gaps at the end (longest-processing-time scheduling). Tests under
`LONG_S` keep collection order, after the long ones.

The expected time of a test is its measured wall time in ``tests/durations.json`` (test id
-> seconds: the slowest tests of a CI run, or every test of ``python -m pytest -n 2
--junitxml=FILE`` through ``python tests/schedule.py FILE``); a test not in it counts
`UNKNOWN_SLOW_S` seconds when marked ``slow`` and `UNKNOWN_S` otherwise. Only the order
changes: every test still runs, each with its own fixtures. Every xdist worker collects
and orders the tests alike (the file and the sort are deterministic), as xdist requires.
"""

from __future__ import annotations

import json
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

DURATIONS = Path(__file__).with_name("durations.json")
UNKNOWN_SLOW_S = 30.0
UNKNOWN_S = 1.0
LONG_S = 10.0  # the tests moved to the front; shorter ones keep their place


def read_durations(path: Path = DURATIONS) -> dict[str, float]:
    """Test id -> measured seconds; empty if the file is missing or unreadable."""
    try:
        return {str(k): float(v) for k, v in json.loads(path.read_text())["seconds"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def expected_seconds(nodeid: str, slow: bool, durations: dict[str, float]) -> float:
    """A test's measured seconds, else the default of its marker."""
    return durations.get(nodeid, UNKNOWN_SLOW_S if slow else UNKNOWN_S)


def longest_first(items: list, durations: dict[str, float]) -> list:
    """The tests of `LONG_S` seconds or more first, longest first; then the others in
    collection order (a file's short tests together, so that its module-scoped fixtures are
    made once per worker, not once per test)."""

    def seconds(item) -> float:
        s = expected_seconds(item.nodeid, item.get_closest_marker("slow") is not None, durations)
        return s if s >= LONG_S else 0.0

    return sorted(items, key=lambda item: -seconds(item))


def from_junit(path: Path) -> dict[str, float]:
    """Test id -> seconds of a junit XML report (pytest's ``--junitxml``): the call's time
    with its fixtures', as pytest writes it."""
    seconds = {}
    for case in ET.parse(path).getroot().iter("testcase"):
        module = case.get("classname", "").replace(".", "/")
        nodeid = f"{module}.py::{case.get('name')}"
        seconds[nodeid] = round(float(case.get("time", 0.0)), 1)
    return seconds


def main(argv: list[str]) -> int:
    """``python tests/schedule.py JUNIT.xml``: writes tests/durations.json from the report."""
    if len(argv) != 1 or not Path(argv[0]).is_file():
        print("usage: python tests/schedule.py JUNIT.xml (a report of pytest --junitxml)", file=sys.stderr)
        return 2
    seconds = from_junit(Path(argv[0]))
    doc = {"measured": f"every test of {Path(argv[0]).name}", "seconds": dict(sorted(seconds.items()))}
    DURATIONS.write_text(json.dumps(doc, indent=0) + "\n")
    print(f"{len(seconds)} tests, {sum(seconds.values()) / 60:.1f} min in all -> {DURATIONS}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
