"""Shared helpers (testbed.py) for the scenario test directories below."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def pytest_runtest_logreport(report):
    """A failure's traceback, printed as it happens: a CI run cut short by its time limit never reaches
    pytest's summary at the end, and would keep only the word FAILED."""
    if report.failed:
        sys.stderr.write(f"\n---- {report.nodeid} ({report.when}) failed:\n{report.longreprtext[-6000:]}\n----\n")
        sys.stderr.flush()
