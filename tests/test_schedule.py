"""The suite's start order (tests/schedule.py): the long tests first, longest first; the others
in collection order; the measured seconds read from a junit report."""

import json

import schedule


class Item:
    def __init__(self, nodeid, slow=False):
        self.nodeid, self.slow = nodeid, slow

    def get_closest_marker(self, name):
        return object() if name == "slow" and self.slow else None


def test_long_tests_start_first_and_short_ones_keep_their_order():
    names = ["a::short1", "a::long", "b::short2", "b::new_slow", "c::huge"]
    items = [Item(n, slow=n.endswith("slow")) for n in names]
    durations = {"a::long": 60.0, "c::huge": 500.0, "a::short1": 3.0, "b::short2": 9.9}
    order = [i.nodeid for i in schedule.longest_first(items, durations)]
    assert order == ["c::huge", "a::long", "b::new_slow", "a::short1", "b::short2"]


def test_the_committed_durations_name_tests_and_seconds():
    durations = schedule.read_durations()
    assert len(durations) >= 10 and all("::" in k and v > 0 for k, v in durations.items())
    assert schedule.read_durations(schedule.DURATIONS.with_name("absent.json")) == {}


def test_a_junit_report_becomes_test_ids_and_seconds(tmp_path):
    report = tmp_path / "j.xml"
    report.write_text(
        '<testsuites><testsuite><testcase classname="tests.test_x" name="test_y[a-1]" time="12.34"/>'
        '<testcase classname="tests.test_z" name="test_w" time="0.5"/></testsuite></testsuites>'
    )
    expected = {"tests/test_x.py::test_y[a-1]": 12.3, "tests/test_z.py::test_w": 0.5}
    assert schedule.from_junit(report) == expected
    assert json.loads(schedule.DURATIONS.read_text())["measured"]
