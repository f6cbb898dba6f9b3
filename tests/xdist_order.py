"""How the two pytest-xdist workers share the tests (``--dist loadfile``, see pyproject.toml):
longest first.

pytest-xdist hands out whole test files (module fixtures are built once) in the order of their
number of tests, so a file of a few long tests (the notebooks, the README tour, a learn on
the salsa clips) could start last and leave one worker running alone at the end. Here the
files go out longest first (the longest-processing-time rule: what is left at the end is
short, so the workers finish together), by the seconds of ``durations.json``: for each test of
at least 3 s, its CPU seconds (with its child processes) in a run on the 2-core machine; a
test not listed counts :data:`SHORT` seconds. A few long tests of one file that need nothing
of each other (:data:`OWN_UNIT`) go out one by one.

The table only orders the work: a stale entry costs time, never a test.
"""

from __future__ import annotations

import json
from pathlib import Path

from xdist.scheduler import LoadFileScheduling

#: seconds of a test not in durations.json
SHORT = 0.5

#: node id prefixes of tests that are a unit of work each rather than part of their file's:
#: the four kinds of slow fuzzing (each minutes long, sharing only a small fixture)
OWN_UNIT: tuple[str, ...] = ("tests/test_fuzz.py::test_fuzz_slow[",)

SECONDS: dict[str, float] = json.loads(
    (Path(__file__).with_name("durations.json")).read_text(encoding="utf-8")
)


def expected_seconds(nodeids: list[str] | dict[str, bool]) -> float:
    """The expected time of a unit of work: the sum over its tests."""
    return sum(SECONDS.get(n, SHORT) for n in nodeids)


class LongestFirst(LoadFileScheduling):
    """``--dist loadfile`` with the files handed out longest first."""

    _ordered = False

    def _split_scope(self, nodeid: str) -> str:
        if nodeid.startswith(OWN_UNIT):
            return nodeid
        return super()._split_scope(nodeid)

    def _assign_work_unit(self, node) -> None:
        if not self._ordered:  # the first call: the queue holds every unit
            units = sorted(self.workqueue.items(), key=lambda u: -expected_seconds(u[1]))
            self.workqueue.clear()
            self.workqueue.update(units)
            self._ordered = True
        super()._assign_work_unit(node)
