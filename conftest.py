"""pytest, whole repository: the doctests of the mapped folders under their installed names.

``storage/``, ``tasks/`` and ``flows/`` are the packages ``tumor3d.storage``,
``tumor3d.tasks`` and ``tumor3d.flows`` (pyproject.toml's ``package-dir``,
:mod:`tumor3d.package_layout`). pytest names a module after its path
(``flows/cli/app.py`` would be ``flows.cli.app``) and would import a second
copy of it under that name for ``--doctest-modules`` (``make test``). Here that
name is bound to the module imported by its installed name first, so the
doctests run in the modules the program uses and are named after them
(``flows/cli/app.py::tumor3d.flows.cli.app...``). The tests' own fixtures are
in ``tests/conftest.py``.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

from tumor3d.package_layout import MAPPED_PACKAGES, PACKAGE_DIRS, PROJECT_ROOT

#: Folder -> package, for the packages that lie under another name than their own.
_MAPPED = {
    (PROJECT_ROOT / PACKAGE_DIRS[name]).resolve(): name
    for name in MAPPED_PACKAGES
    if PACKAGE_DIRS[name].parts != tuple(name.split("."))
}


def pytest_collect_file(file_path: Path, parent) -> None:
    """Before pytest imports a mapped module for its doctests, name it as installed.

    Returns None: pytest's own doctest collector collects the file.
    """
    if file_path.suffix != ".py" or file_path.name == "__main__.py":
        return None
    if not parent.config.getoption("doctestmodules", False):
        return None
    path = file_path.resolve()
    for folder, package in _MAPPED.items():
        if folder != path.parent and folder not in path.parents:
            continue
        rest = path.relative_to(folder).with_suffix("").parts
        rest = rest[:-1] if rest[-1] == "__init__" else rest
        path_name = ".".join((*folder.relative_to(PROJECT_ROOT).parts, *rest))
        try:
            module = importlib.import_module(".".join((package, *rest)))
        except Exception:  # pytest's own import reports it
            return None
        sys.modules.setdefault(path_name, module)
        return None
    return None
