"""Progress reporting from runners and flows to whoever is watching (the CLI).

Flows call :func:`report`; the CLI installs a reporter with
:func:`use_reporter`. With none installed, reports are dropped, so flows run
unchanged under a scheduler or in tests.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

__all__ = ["ProgressEvent", "report", "use_reporter"]


@dataclass(frozen=True)
class ProgressEvent:
    """One step of a flow: ``status`` is ``started``, ``done`` or ``cached``."""

    patient_id: str
    stage: str
    status: str
    index: int
    total: int
    seconds: float = 0.0


Reporter = Callable[[ProgressEvent], None]
_reporter: ContextVar[Reporter | None] = ContextVar("tumor3d_reporter", default=None)


def report(event: ProgressEvent) -> None:
    """Send an event to the installed reporter, if any."""
    fn = _reporter.get()
    if fn is not None:
        fn(event)


@contextmanager
def use_reporter(fn: Reporter) -> Iterator[None]:
    """Install ``fn`` as the reporter for the duration of the block."""
    token = _reporter.set(fn)
    try:
        yield
    finally:
        _reporter.reset(token)
