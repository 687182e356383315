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


# The files that take longest, longest first (issue 31 item 7: per-file sums of the test
# times of two full runs, before and after the runs they share were merged; the load
# moved them by up to 2x): numba kernels compiled for a test's own reference loop and
# index types, S3 cohorts and Dask worker processes, Dask workers killed and restarted,
# evaluation flows, a numba warm-up into a new cache, one patient flow run that many
# tests read, a cohort command interrupted and re-run, real Prefect servers, training
# flows, code closures of package copies, cohorts, trained models, published folders.
LONGEST_FILES = ("test_simplify_speed_equivalence.py", "test_objectstore.py", "test_dask.py",
                 "test_evaluate_flow.py", "test_warmup.py", "test_patient_flow.py",
                 "test_cohort_interrupt.py", "test_server.py", "test_train_flow.py",
                 "test_caching.py", "test_cohort_flow.py", "test_learned.py",
                 "test_adapters.py", "test_publish_current.py", "test_serve.py",
                 "test_layout_invariance.py", "test_viewer.py", "test_brain_mask_flow.py",
                 "test_records.py", "test_daemon.py", "test_cli_environment.py",
                 "test_lesion.py")  # fmt: skip


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


def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` that gives a worker its next file when one test of its current
    file is left to run, not two (xdist's own rule).

    A worker takes its next file before it frees up (it runs a test only once it knows
    the next one); with two tests left it could take the next long file while its last
    two (in test_objectstore.py, test_dask.py or test_warmup.py: minutes) still ran and
    the other worker was about to be idle. Any other ``--dist``: xdist's own scheduler.
    """
    if config.getoption("dist", None) != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class NextFileAtTheLastTest(LoadFileScheduling):
        def _reschedule(self, node):
            if node.shutting_down:
                return
            if not self.workqueue:
                node.shutdown()
                return
            if self._pending_of(self.assigned_work[node]) > 1:
                return
            self._assign_work_unit(node)

    return NextFileAtTheLastTest(config, log)


def pytest_sessionfinish(session, exitstatus):
    shutil.rmtree(_PREFECT_HOME, ignore_errors=True)
