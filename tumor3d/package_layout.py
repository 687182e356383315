"""Where the packages of the ``tumor3d`` namespace lie on disk (issue 31 item 6).

The distribution installs one top-level package, ``tumor3d``. The repository
keeps the three upper layers in top-level folders of their own, mapped into
the namespace by ``[tool.setuptools] package-dir`` in pyproject.toml:
``storage/`` is ``tumor3d.storage``, ``tasks/`` is ``tumor3d.tasks`` and
``flows/`` is ``tumor3d.flows``. A built wheel nests them under ``tumor3d/``
as usual; an editable install (``pip install -e .``, ``make setup``) finds
them through the mapping. Code that reads the project's source files (the
cache keys' code digests, the warm runner's fingerprint, the layer test)
asks here where a module's file is instead of joining ``tumor3d/...``.

Only the standard library is imported (the console script imports this).

>>> PACKAGE_DIRS["tumor3d"]
PosixPath('tumor3d')
>>> module_path("tumor3d.imaging.scan")
PosixPath('tumor3d/imaging/scan')
>>> (PROJECT_ROOT / module_path("tumor3d.package_layout")).with_suffix(".py") == Path(__file__)
True
"""

from __future__ import annotations

from importlib.util import find_spec
from pathlib import Path

__all__ = ["MAPPED_PACKAGES", "PACKAGE_DIRS", "PROJECT_ROOT", "SOURCE_FOLDERS", "module_path"]

#: The sub-packages the repository keeps in top-level folders (pyproject.toml's
#: ``package-dir``), lowest layer first.
MAPPED_PACKAGES = ("tumor3d.storage", "tumor3d.tasks", "tumor3d.flows")

#: The folder holding the ``tumor3d`` package: the repository's root, or
#: site-packages when installed from a wheel.
PROJECT_ROOT = Path(__file__).resolve().parent.parent


def _package_dir(name: str) -> Path:
    """The folder of package ``name``, as the import system finds it (not imported)."""
    spec = find_spec(name)
    if spec is None or spec.origin is None or not spec.submodule_search_locations:
        where = list(spec.submodule_search_locations or []) if spec is not None else []
        raise ImportError(
            f"{name} is not installed as a package (found: {where or 'nothing'}): reinstall "
            "tumor3d (make setup, or pip install -e .); a folder of that name left under "
            "tumor3d/ by an old checkout (only __pycache__ in it) hides it: remove it"
        )
    return Path(spec.origin).resolve().parent


def _relative(folder: Path) -> Path:
    try:
        return folder.relative_to(PROJECT_ROOT)
    except ValueError:  # installed apart from tumor3d/ (not by this project's builds)
        return folder


#: Each package's folder relative to :data:`PROJECT_ROOT`: ``tumor3d`` and the
#: :data:`MAPPED_PACKAGES` (``tasks`` in the repository, ``tumor3d/tasks`` installed).
PACKAGE_DIRS: dict[str, Path] = {
    "tumor3d": Path("tumor3d"),
    **{name: _relative(_package_dir(name)) for name in MAPPED_PACKAGES},
}

#: The folders that hold all of the project's code, none inside another:
#: ``tumor3d``, ``storage``, ``tasks``, ``flows`` in the repository; ``tumor3d`` installed.
SOURCE_FOLDERS: tuple[Path, ...] = tuple(
    folder
    for folder in dict.fromkeys(PACKAGE_DIRS.values())
    if not any(other != folder and other in folder.parents for other in PACKAGE_DIRS.values())
)


def module_path(name: str) -> Path:
    """Where module or package ``name`` lies under :data:`PROJECT_ROOT`, without suffix.

    The longest package of :data:`PACKAGE_DIRS` that ``name`` is in gives the
    folder: ``tumor3d.tasks.caching`` is ``tasks/caching`` in the repository
    and ``tumor3d/tasks/caching`` when installed. Add ``.py`` for a module,
    ``/__init__.py`` for a package. Names outside the namespace map as dotted.
    """
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        folder = PACKAGE_DIRS.get(".".join(parts[:i]))
        if folder is not None:
            return folder.joinpath(*parts[i:])
    return Path(*parts)
