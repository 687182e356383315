"""Progress reporting (re-exported from :mod:`tumor3d.tasks.progress`, where runners report)."""

from tumor3d.tasks.progress import ProgressEvent, report, use_reporter

__all__ = ["ProgressEvent", "report", "use_reporter"]
