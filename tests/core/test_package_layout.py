"""One installed namespace, with the repository's top-level folders (issue 31 item 6).

``storage/``, ``tasks/`` and ``flows/`` are ``tumor3d.storage``, ``tumor3d.tasks``
and ``tumor3d.flows`` through pyproject.toml's ``package-dir``; the build lists
every package and data folder (``packages.find`` cannot rename a folder), so a
new sub-package left out of the list would be missing from a wheel while the
editable install still found it: checked here.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import tomllib
from pathlib import Path

from tumor3d.package_layout import MAPPED_PACKAGES, PACKAGE_DIRS, PROJECT_ROOT, SOURCE_FOLDERS

SETUPTOOLS = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def _packages_on_disk() -> set[str]:
    """Every folder, as ``packages.find`` with namespaces listed them (data folders too)."""
    found = set()
    for package, folder in PACKAGE_DIRS.items():
        base = PROJECT_ROOT / folder
        for d in [base, *base.rglob("*")]:
            rest = d.relative_to(base).parts
            if d.is_dir() and all(p.isidentifier() and p != "__pycache__" for p in rest):
                found.add(".".join((package, *rest)))
    return found


def test_the_build_lists_every_package_of_the_folders_and_no_other():
    assert set(SETUPTOOLS["packages"]) == _packages_on_disk()
    assert all(p == "tumor3d" or p.startswith("tumor3d.") for p in SETUPTOOLS["packages"])


def test_the_build_maps_the_folders_the_code_finds():
    assert SETUPTOOLS["package-dir"] == {name: name.split(".")[-1] for name in MAPPED_PACKAGES}
    assert {name: str(PACKAGE_DIRS[name]) for name in MAPPED_PACKAGES} == SETUPTOOLS["package-dir"]
    assert [str(f) for f in SOURCE_FOLDERS] == ["tumor3d", "storage", "tasks", "flows"]
    for name in MAPPED_PACKAGES:  # imported from the mapped folder, under its installed name
        module = importlib.import_module(name)
        assert Path(module.__file__).resolve() == PROJECT_ROOT / PACKAGE_DIRS[name] / "__init__.py"


def test_only_tumor3d_is_importable_outside_the_repository(tmp_path):
    code = (
        "import importlib.util as u, tumor3d.flows.daemon, tumor3d.tasks, tumor3d.storage;"
        "print([u.find_spec(n) for n in ('flows', 'tasks', 'storage')])"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[None, None, None]"
