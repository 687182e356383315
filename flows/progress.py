"""Progress reporting (re-exported from :mod:`tasks.progress`, where runners report)."""

from tasks.progress import ProgressEvent, report, use_reporter

__all__ = ["ProgressEvent", "report", "use_reporter"]
