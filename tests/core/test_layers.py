"""The layers of the one ``tumor3d`` namespace import downwards only (issue 31).

``tumor3d.flows`` (wiring, CLI) -> ``tumor3d.tasks`` (stage adapters, cache keys)
-> ``tumor3d.storage`` (all file I/O) -> the core (every other module: arrays in,
results out, no Prefect, no file I/O). ``tumor3d.api``, the notebook facade
that also takes file names, and ``tumor3d.warmup`` (which runs it) sit on the
storage layer. Read from the source's syntax trees, every
import statement (top level and inside functions), so a lazy import counts too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tumor3d.package_layout import PACKAGE_DIRS, PROJECT_ROOT

#: Layer of each sub-package; the core is everything else (rank 0).
RANK = {"storage": 1, "tasks": 2, "flows": 3}
#: Modules outside those sub-packages with a layer of their own.
MODULE_RANK = {"tumor3d.api": RANK["storage"], "tumor3d.warmup": RANK["storage"]}
#: Third-party packages only the orchestration layers may import.
ORCHESTRATION = ("prefect", "prefect_dask", "distributed", "dask")


def _layer(module: str) -> int:
    for name, rank in MODULE_RANK.items():
        if module == name or module.startswith(name + "."):
            return rank
    parts = module.split(".")
    return RANK.get(parts[1], 0) if parts[0] == "tumor3d" and len(parts) > 1 else 0


def _imports(path: Path, module: str) -> set[str]:
    tree = ast.parse(path.read_bytes(), filename=str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, *([node.module] if node.module else [])])
            else:
                base = node.module or ""
            found.add(base)
            found.update(f"{base}.{a.name}" for a in node.names)
    return found


def _modules() -> list[tuple[str, Path]]:
    # tumor3d/ and the folders mapped into the namespace (storage/, tasks/, flows/)
    out = {}
    for package, folder in PACKAGE_DIRS.items():
        for path in sorted((PROJECT_ROOT / folder).rglob("*.py")):
            rel = path.relative_to(PROJECT_ROOT / folder).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            out[".".join((package, *parts))] = path
    return sorted(out.items())


def _violations(modules: list[tuple[str, Path]]) -> list[str]:
    bad = []
    for module, path in modules:
        if module in ("tumor3d", "tumor3d.__main__"):
            continue  # the root's PEP 562 __getattr__ re-exports the facade; the CLI's entry
        rank = _layer(module)
        for name in _imports(path, module):
            if name.startswith("tumor3d.") and _layer(name) > rank:
                bad.append(f"{module} imports {name} (a higher layer)")
            if rank < RANK["tasks"] and name.split(".")[0] in ORCHESTRATION:
                bad.append(f"{module} imports {name} (orchestration below tasks)")
    return bad


def test_every_module_imports_only_its_own_layer_or_lower():
    modules = _modules()
    assert len(modules) > 60 and {_layer(m) for m, _ in modules} == {0, 1, 2, 3}
    assert _violations(modules) == []


@pytest.mark.parametrize(
    "source, expected",
    [
        ("from tumor3d.flows.cli import main\n", "a higher layer"),
        ("def f():\n    from .storage import nifti\n", "a higher layer"),
        ("import tumor3d.api\n", "a higher layer"),
        ("import prefect\n", "orchestration below tasks"),
    ],
)
def test_an_upward_import_is_caught(tmp_path, source, expected):
    # the checker itself: a core module with an upward import (lazy and relative too)
    path = tmp_path / "probe.py"
    path.write_text(source)
    bad = _violations([("tumor3d.segmentation_probe", path)])
    assert bad and all(expected in b for b in bad)


#: Issue 31 item 5: no module over about 600 lines, so that each holds one concept.
MAX_MODULE_LINES = 650  # the longest: config.py 623, tasks/caching.py 615


def test_no_module_is_longer_than_one_concept_needs():
    long = {
        str(path.relative_to(PROJECT_ROOT)): n
        for _, path in _modules()
        if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES
    }
    assert not long, f"split by concept (docs/ARCHITECTURE.md): {long}"
