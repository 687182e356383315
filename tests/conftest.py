"""Session-wide test set-up.

Prefect runs against a throw-away home folder (never the user's
~/.prefect), with analytics off; flow tests share one temporary Prefect
server started by ``prefect_test_harness`` with a generous start-up timeout,
on a copy of a database migrated once per session, recording task runs in
batches and keeping no event history; their flow runs send no heartbeats.
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
import sqlite3
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

_PREFECT_HOME = tempfile.mkdtemp(prefix="tumor3d-test-prefect-")
os.environ["PREFECT_HOME"] = _PREFECT_HOME
os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] = "false"
os.environ["PREFECT_LOGGING_LEVEL"] = "WARNING"
os.environ.pop("PREFECT_API_URL", None)
# Every Prefect server the tests start (the harness's, and the temporary ones of the CLI
# commands they run) inherits this: its task-run recorder writes the stage task runs in
# batches every second instead of one SQLite transaction per event. One transaction per
# event made the next flow run's creation collide with it ("database is locked", SQLite's
# deferred-transaction upgrade, answered 503) about every other back-to-back run, and the
# client's retry waits 2 s; without flow-run heartbeats (below) nothing spaces the runs.
# The task runs are still recorded, up to a second after their flow run ends. (Prefect
# reads the interval as a whole number of seconds: 0.5 would be 0, a busy loop.)
os.environ["PREFECT_SERVER_SERVICES_TASK_RUN_RECORDER_BATCH_SIZE"] = "200"
os.environ["PREFECT_SERVER_SERVICES_TASK_RUN_RECORDER_READ_BATCH_SIZE"] = "200"
os.environ["PREFECT_SERVER_SERVICES_TASK_RUN_RECORDER_FLUSH_INTERVAL"] = "1"
# ... and keeps no event history, evaluates no automation and streams no event out: no test
# reads them, and they were ~45 % of a test server's CPU time per flow run.
os.environ["PREFECT_SERVER_SERVICES_EVENT_PERSISTER_ENABLED"] = "false"
os.environ["PREFECT_SERVER_SERVICES_TRIGGERS_ENABLED"] = "false"
os.environ["PREFECT_SERVER_EVENTS_STREAM_OUT_ENABLED"] = "false"


def _one_certificate_ca_file(folder: str) -> str:
    """A CA file of one certificate: the first of certifi's bundle."""
    import certifi

    bundle = Path(certifi.where()).read_text()
    end = "-----END CERTIFICATE-----"
    first = bundle[bundle.index("-----BEGIN CERTIFICATE-----") : bundle.index(end) + len(end)]
    path = Path(folder) / "one-certificate.pem"
    path.write_text(first + "\n")
    return str(path)


# Every Prefect client builds an SSL context, from PREFECT_API_SSL_CERT_FILE or else from
# certifi's bundle of ~140 certificates: 15-22 ms a client (skipping TLS verification loads
# the system's bundle instead, as slow), and a run makes about 700 clients. The tests'
# servers are plain http, so no handshake ever reads the file: one certificate makes a
# context in 0.3 ms.
os.environ.setdefault("PREFECT_API_SSL_CERT_FILE", _one_certificate_ca_file(_PREFECT_HOME))

import pytest  # noqa: E402

PREFECT_STARTUP_TIMEOUT_S = 120

# A Prefect database with every migration applied, made once per session and copied in
# before each test server starts: a server on a new database spends ~4 of its ~8 CPU-s of
# start-up migrating it (once per xdist worker, and once per temporary server of a CLI
# command on the worker's PREFECT_HOME). The folder is the session's (made by the process
# that starts it, the xdist controller, before the workers start; they find it in the
# environment). The migration (Prefect's own command, ~9 CPU-s, 12 s) depends only on the
# installed Prefect, Python and SQLite, so the template is also kept in pytest's cache
# folder under those versions and copied from there by the next session. Under xdist the
# controller makes it in a background thread from the start, while the workers start and
# collect (they wait for it at their first test server); a single process makes it at its
# first test server. A build that fails leaves ``failed`` in the session's folder and the
# servers migrate their own databases as before; a kept copy that is not sound (or on which
# the test server fails to start) is not used again.
_DB_TEMPLATE_ENV = "TUMOR3D_TEST_PREFECT_DB_FOLDER"
_DB_TEMPLATE_OWNER = False
_DB_CACHE_ENV = "TUMOR3D_TEST_PREFECT_DB_CACHE"  # the kept templates' folder, if any
_DB_BUILD: dict = {}  # the controller's background build: thread, subprocess, stop flag
_DB_BUILD_LOCK = threading.Lock()


def _template_cache_file() -> Path | None:
    """The kept template of the installed Prefect, Python and SQLite (None: no cache)."""
    from importlib.metadata import version

    folder = os.environ.get(_DB_CACHE_ENV)
    if not folder:
        return None
    py = "{}.{}".format(*sys.version_info[:2])
    return Path(folder) / f"prefect-{version('prefect')}-py{py}-sqlite{sqlite3.sqlite_version}.db"


def _is_migrated(db: Path) -> bool:
    """True if ``db`` is a sound SQLite file that Prefect's migrations have stamped."""
    try:
        with sqlite3.connect(f"file:{db}?mode=ro&immutable=1", uri=True) as con:
            if con.execute("PRAGMA quick_check").fetchone() != ("ok",):
                return False
            return bool(con.execute("SELECT version_num FROM alembic_version").fetchall())
    except sqlite3.Error:
        return False


def forget_kept_template() -> None:
    """Remove the kept template (a test server failed to start on a copy of it)."""
    kept = _template_cache_file()
    if kept is not None:
        kept.unlink(missing_ok=True)


def _migrate(folder: Path, build: Path) -> bool:
    """Prefect's own migration command on ``build``; False if it fails or is stopped."""
    with _DB_BUILD_LOCK:
        if _DB_BUILD.get("stop"):
            return False
        proc = subprocess.Popen(
            [sys.executable, "-m", "prefect", "server", "database", "upgrade", "-y"],
            env={**os.environ, "PREFECT_HOME": str(folder / "home"),
                 "PREFECT_SERVER_DATABASE_CONNECTION_URL": f"sqlite+aiosqlite:///{build}"},
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        _DB_BUILD["proc"] = proc
    try:
        return proc.wait(timeout=600) == 0 and _is_migrated(build)
    finally:
        if proc.poll() is None:  # a timeout, an interrupt: never left behind
            proc.kill()
            proc.wait()


def _build_template(folder: Path) -> None:
    """Make ``folder/template.db`` (caller holds the folder's lock): from the kept copy, or
    by Prefect's migration (kept for the next session); ``failed`` if that fails."""
    template, build = folder / "template.db", folder / "build.db"
    kept = _template_cache_file()
    if kept is not None and kept.is_file() and _is_migrated(kept):
        shutil.copyfile(kept, build)
        build.replace(template)
        return
    try:
        migrated = _migrate(folder, build)
    except (OSError, subprocess.SubprocessError):
        migrated = False
    if not migrated:
        (folder / "failed").touch()
        return
    build.replace(template)  # whole, or not at all
    if kept is not None:  # kept whole too: a copy renamed into place
        try:
            kept.parent.mkdir(parents=True, exist_ok=True)
            part = kept.with_name(f".{kept.name}.{os.getpid()}")
            shutil.copyfile(template, part)
            part.replace(kept)
        except OSError:
            pass


def pytest_configure(config):
    global _DB_TEMPLATE_OWNER
    # Commands whose Ctrl-C the tests check are started as from a terminal: a suite
    # launched with SIGINT ignored (a shell script's background job, `cmd &`) would hand
    # that on to them, and a command started so keeps ignoring SIGINT by design
    # (tumor3d.flows.cli.errors._ctrl_c_ends). Every process of the suite (xdist's
    # workers run this too) takes Python's own handler, so its children start with the
    # default.
    import signal

    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if _DB_TEMPLATE_ENV in os.environ:  # an xdist worker: the controller made the folder
        return
    import fcntl

    folder = Path(tempfile.mkdtemp(prefix="tumor3d-test-prefect-db-"))
    os.environ[_DB_TEMPLATE_ENV] = str(folder)
    _DB_TEMPLATE_OWNER = True
    cache = getattr(config, "cache", None)  # None with -p no:cacheprovider
    try:
        if cache is not None:
            os.environ[_DB_CACHE_ENV] = str(cache.mkdir("tumor3d-prefect-db"))
    except OSError:  # a read-only checkout, a cache_dir that cannot be made: no kept copy
        pass
    if not getattr(config.option, "numprocesses", None) or getattr(config.option, "help", False):
        return  # one process: the template is made at its first test server
    lock = open(folder / "lock", "w")  # held from here: the workers wait for the build
    fcntl.flock(lock, fcntl.LOCK_EX)

    def build():
        try:
            _build_template(folder)
        except Exception:  # a session ended under it (its folder removed): servers migrate
            pass
        finally:
            lock.close()  # releases the lock

    thread = threading.Thread(target=build, name="prefect-db-template", daemon=True)
    _DB_BUILD["thread"] = thread
    thread.start()


def pytest_unconfigure(config):
    """End the controller's build if the session ends first (a few quick tests, ``--help``)
    and remove the session's folder (the process that made it)."""
    with _DB_BUILD_LOCK:
        _DB_BUILD["stop"] = True
        proc = _DB_BUILD.get("proc")
        if proc is not None and proc.poll() is None:
            proc.kill()
    thread = _DB_BUILD.get("thread")
    if thread is not None:
        thread.join(timeout=10)
    if _DB_TEMPLATE_OWNER:
        shutil.rmtree(os.environ[_DB_TEMPLATE_ENV], ignore_errors=True)


def migrated_prefect_db() -> Path | None:
    """The session's migrated Prefect database, made here if no process has yet."""
    import fcntl

    folder = Path(os.environ[_DB_TEMPLATE_ENV])
    template = folder / "template.db"
    with open(folder / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one makes it, the others wait for it
        if template.is_file():
            return template
        if (folder / "failed").exists():
            return None
        _build_template(folder)
        return template if template.is_file() else None


def seed_prefect_db(dest: Path) -> bool:
    """Copy the migrated database to ``dest`` (a server's database file) if there is one."""
    template = migrated_prefect_db()
    if template is None or dest.exists():
        return False
    dest.parent.mkdir(parents=True, exist_ok=True)
    with sqlite3.connect(template) as src, sqlite3.connect(dest) as dst:
        src.backup(dst)
    return True


@pytest.fixture
def seed_prefect_home():
    """``seed(home)``: give a test's own ``PREFECT_HOME`` the session's migrated database
    (above), for the temporary server a CLI command run with that home starts."""

    def seed(home: Path) -> Path:
        seed_prefect_db(Path(home) / "prefect.db")
        return Path(home)

    return seed


@pytest.fixture(scope="session")
def prefect_harness():
    """One temporary Prefect server for the whole session, flow runs without heartbeats.

    As the CLI runs its commands (``tumor3d.flows.cli.session``): Prefect's heartbeat
    thread sleeps in 1 s steps and the engine joins it at the end of every flow run,
    about 0.8 s of idle wall time per run, for a signal no test uses.
    """
    import prefect.testing.utilities as harness
    from prefect.settings import temporary_settings

    # the temporary servers of CLI commands use this process's PREFECT_HOME database
    seed_prefect_db(Path(_PREFECT_HOME) / "prefect.db")

    def seeded_mkdtemp(*args, **kwargs):  # the folder of the harness's prefect-test.db
        folder = tempfile.mkdtemp(*args, **kwargs)
        seed_prefect_db(Path(folder) / "prefect-test.db")
        return folder

    original, harness.mkdtemp = harness.mkdtemp, seeded_mkdtemp
    started = False
    try:
        with (
            harness.prefect_test_harness(server_startup_timeout=PREFECT_STARTUP_TIMEOUT_S),
            temporary_settings(updates={"flows.heartbeat_frequency": None}),
        ):
            started = True
            yield
    except Exception:
        if not started:  # on a copy of the kept template: the next session migrates anew
            forget_kept_template()
        raise
    finally:
        harness.mkdtemp = original


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
