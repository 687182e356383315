"""Session-wide test set-up.

Prefect runs against a throw-away home folder (never the user's
~/.prefect), with analytics off; flow tests share one temporary Prefect
server started by ``prefect_test_harness`` with a generous start-up timeout.
These variables must be set before Prefect is first imported.

Under pytest-xdist (``make test``: ``-n 2 --dist loadfile``) every worker is its
own process that imports this file: its own Prefect home, its own test server,
its own temporary folders. The numba kernels are read from the cache that
``python -m tumor3d.warmup`` filled at install time (numba writes a cache entry
to a temporary file and renames it, so two workers compiling one kernel do not
corrupt it).
"""

from __future__ import annotations

import os
import shutil
import tempfile

_PREFECT_HOME = tempfile.mkdtemp(prefix="tumor3d-test-prefect-")
os.environ["PREFECT_HOME"] = _PREFECT_HOME
os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] = "false"
os.environ["PREFECT_LOGGING_LEVEL"] = "WARNING"
os.environ.pop("PREFECT_API_URL", None)

import pytest  # noqa: E402

PREFECT_STARTUP_TIMEOUT_S = 120


@pytest.fixture(scope="session")
def prefect_harness():
    """One temporary Prefect server for the whole session."""
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=PREFECT_STARTUP_TIMEOUT_S):
        yield


# The files that take longest (one to five minutes each on 2 busy cores: S3 cohorts and
# Dask worker processes, one patient flow run that many tests read, Dask worker processes
# killed and restarted, cohorts, evaluation flows, a numba warm-up into a new cache, a
# cohort command interrupted and re-run), longest first (measured: issue 31, --durations).
LONGEST_FILES = ("test_objectstore.py", "test_patient_flow.py", "test_dask.py",
                 "test_cohort_flow.py", "test_caching.py", "test_evaluate_flow.py",
                 "test_warmup.py", "test_cohort_interrupt.py", "test_records.py",
                 "test_adapters.py")  # fmt: skip


def pytest_collection_modifyitems(config, items):
    """The longest files, then the other files with ``slow`` tests, then the rest.

    With ``--dist loadfile`` a worker takes whole files as it frees up: the long
    files first and the many short ones after them keep both workers busy to the
    end (a long file started last would leave the other worker idle). Every
    worker collects the same items and sorts them the same way; xdist keeps this
    order only with ``--no-loadscope-reorder`` (``make test``), else it orders the
    files by their number of tests.
    """
    slow_files = {item.path for item in items if item.get_closest_marker("slow")}

    def rank(item):  # stable sort: the order inside a file is kept
        if item.path.name in LONGEST_FILES:
            return LONGEST_FILES.index(item.path.name)
        return len(LONGEST_FILES) + (item.path not in slow_files)

    items.sort(key=rank)


def pytest_sessionfinish(session, exitstatus):
    shutil.rmtree(_PREFECT_HOME, ignore_errors=True)
