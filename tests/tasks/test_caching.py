"""Cache keys: the real code closure, composable policies, blind to locations and run ids."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from tumor3d.config import SimplifyConfig
from tumor3d.package_layout import SOURCE_FOLDERS
from tumor3d.storage.store import ArtifactRef
from tumor3d.tasks.caching import (
    FORMAT_MODULES,
    PROJECT_PACKAGES,
    PROJECT_ROOT,
    InputArtifacts,
    StageCode,
    StageConfig,
    _module_file,
    code_digest,
    fingerprint,
    module_closure,
    stage_cache_policy,
)
from tumor3d.tasks.spec import InputSource
from tumor3d.tasks.stages import STAGES

MODULES = ("tumor3d.tasks.simplify",)


def _key(stage, inputs, modules=MODULES, root=None):
    return stage_cache_policy(stage, modules, root=root).compute_key(None, inputs, {})


def _ref(digest_char: str, suffix: str = ".nii.gz") -> ArtifactRef:
    digest = digest_char * 64
    relpath = f"objects/{digest[:2]}/{digest}{suffix}"
    return ArtifactRef(kind="mask", digest=digest, relpath=relpath, metadata={})


# -- the code closure ---------------------------------------------------------


_PROBE = """
import importlib, json, sys
packages = tuple(sys.argv[1].split(","))
out = {}
for module in sys.argv[2:]:
    for name in [m for m in sys.modules if m.split(".")[0] in packages]:
        del sys.modules[name]
    importlib.import_module(module)
    out[module] = sorted(m for m in sys.modules if m.split(".")[0] in packages)
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def runtime_imports() -> dict[str, set[str]]:
    """Per adapter, the project modules a fresh import of it loads (a separate interpreter)."""
    adapters = [spec.adapter_module for spec in STAGES.values()]
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, ",".join(PROJECT_PACKAGES), *adapters],
        capture_output=True, text=True, check=True, cwd=PROJECT_ROOT,
        env={"PYTHONPATH": str(PROJECT_ROOT), "PATH": "/usr/bin:/bin",
             "HOME": os.environ.get("PREFECT_HOME", "/tmp"),
             "PREFECT_HOME": os.environ.get("PREFECT_HOME", "/tmp/tumor3d-probe-prefect")},
    )  # fmt: skip
    return {k: set(v) for k, v in json.loads(out.stdout.strip().splitlines()[-1]).items()}


@pytest.mark.parametrize("stage", list(STAGES))
def test_closure_holds_every_module_the_adapter_imports(stage, runtime_imports):
    spec = STAGES[stage]
    closure = set(spec.code_modules)
    loaded = runtime_imports[spec.adapter_module]
    assert spec.adapter_module in loaded and spec.entry.__module__ in loaded
    assert loaded <= closure, f"imported but not in the digest: {sorted(loaded - closure)}"
    assert "tumor3d.tasks.stages" not in closure


def test_closure_follows_the_imports_the_old_table_missed():
    assert "tumor3d.imaging.scan" in STAGES["extract-surface"].code_modules  # zyx_index_to_ras
    assert "tumor3d.imaging.scan" in STAGES["simplify-mesh"].code_modules
    assert "tumor3d.imaging.scan" in STAGES["measure-volume"].code_modules
    for stage in STAGES.values():  # every volume write goes through it
        assert "tumor3d.storage.nifti" in stage.code_modules, stage.name


def test_closure_holds_a_packages_lazy_imports_only_when_asked_for_a_lazy_name(package_copy):
    # tumor3d/__init__.py imports tumor3d.api in its PEP 562 __getattr__ (on the first use
    # of tumor3d.reconstruct): `import tumor3d` alone does not run it, so a stage whose
    # code never asks for it does not hold the whole package (issue 31: the right keys move)
    root = str(package_copy)
    probes = {
        "plain": "import tumor3d\n\nVERSION = tumor3d.__version__\n",
        "from_import": "def run(x):\n    from tumor3d import reconstruct\n\n"
                       "    return reconstruct(x)\n",
        "attribute": "import tumor3d\n\n\ndef run(x):\n    return tumor3d.reconstruct(x)\n",
        "aliased": "import tumor3d as t3\n\n\ndef run(x):\n    return t3.Reconstruction\n",
    }  # fmt: skip
    for name, text in probes.items():
        (package_copy / "tasks" / f"probe_{name}.py").write_text(text)
    closures = {n: module_closure((f"tumor3d.tasks.probe_{n}",), root) for n in probes}
    assert "tumor3d.api" not in closures["plain"]
    for name in ("from_import", "attribute", "aliased"):
        assert "tumor3d.api" in closures[name], name
        assert "tumor3d.imaging.scan" in closures[name], name  # and what the api imports
    for spec in STAGES.values():  # no stage asks for the lazy names today
        assert "tumor3d.api" not in spec.code_modules, spec.name


def test_closure_rejects_unknown_module():
    with pytest.raises(ValueError, match="cannot locate"):
        module_closure(("tumor3d.tasks.no_such_adapter",))


@pytest.fixture
def package_copy(tmp_path):
    """A temporary copy of the project packages, with a helper to edit one file."""
    for pkg in SOURCE_FOLDERS:  # tumor3d/ and the folders mapped into it
        shutil.copytree(PROJECT_ROOT / pkg, tmp_path / pkg,
                        ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    yield tmp_path
    module_closure.cache_clear()
    code_digest.cache_clear()


def _keys(root) -> dict[str, str]:
    module_closure.cache_clear()
    code_digest.cache_clear()
    inputs = {"mesh": _ref("a"), "config": SimplifyConfig(), "store_root": "/s"}
    return {
        name: _key(name, inputs, (spec.adapter_module,), root=str(root))
        for name, spec in STAGES.items()
    }


#: A behaviour edit: a new module-level constant (a new name in the module's syntax tree).
_BEHAVIOUR_EDIT = "\n_CACHE_KEY_PROBE = 1\n"


@pytest.mark.parametrize(
    "module",
    ["tumor3d.imaging.scan", "tumor3d.simplify.qem", "tumor3d.storage.nifti", "tumor3d.metrics",
     "tumor3d.tasks.surface", "tumor3d.segmentation.detect", "tumor3d.storage.readers",
     "tumor3d.errors"],
)  # fmt: skip
def test_editing_a_module_changes_exactly_the_keys_whose_closure_holds_it(package_copy, module):
    before = _keys(package_copy)
    target = _module_file(module, package_copy)
    target.write_text(target.read_text() + _BEHAVIOUR_EDIT)
    after = _keys(package_copy)
    changed = {n for n in STAGES if before[n] != after[n]}
    expected = {
        n for n, spec in STAGES.items()
        if module in module_closure((spec.adapter_module,), str(package_copy))
    }  # fmt: skip
    assert expected, f"no stage imports {module}?"
    assert changed == expected


def test_a_behaviour_edit_in_one_adapter_invalidates_only_that_stage(package_copy):
    before = _keys(package_copy)
    f = package_copy / "tasks" / "render.py"
    f.write_text(f.read_text() + _BEHAVIOUR_EDIT)
    after = _keys(package_copy)
    assert {n for n in STAGES if before[n] != after[n]} == {"render-views"}


# -- code digests from the syntax tree (issue 31) -------------------------------

#: Appended to tumor3d/imaging/scan.py: a constant, a function with a docstring and a comment.
_SCAN_PROBE = '''

_PROBE_LIMIT = 2


def _probe(a, b):
    """Sum of two numbers."""
    return a + b  # the sum
'''


def _edit_scan(root, text: str) -> None:
    target = _module_file("tumor3d.imaging.scan", root)
    target.write_text(text)


@pytest.fixture
def scan_probe(package_copy):
    """A package copy whose tumor3d/imaging/scan.py ends with :data:`_SCAN_PROBE`; its text."""
    target = _module_file("tumor3d.imaging.scan", package_copy)
    original = target.read_text() + _SCAN_PROBE
    target.write_text(original)
    return package_copy, original


#: Edits that change no behaviour: (id, old text, new text), the first occurrence replaced.
_NEUTRAL_EDITS = [
    ("comment", "# the sum", "# a + b, the sum of both"),
    ("new-comment-line", "_PROBE_LIMIT = 2\n", "_PROBE_LIMIT = 2\n# a new comment line\n"),
    ("blank-lines", "\n\ndef _probe", "\n\n\n\n\ndef _probe"),
    ("docstring", "Sum of two numbers.", "Add ``a`` and ``b``."),
    ("docstring-removed", '    """Sum of two numbers."""\n', ""),
    ("module-docstring", '"""', '"""Edited: '),
    ("layout", "return a + b  # the sum", "return (a\n            + b)"),
]


@pytest.mark.parametrize(("old", "new"), [e[1:] for e in _NEUTRAL_EDITS],
                         ids=[e[0] for e in _NEUTRAL_EDITS])  # fmt: skip
def test_comments_docstrings_and_layout_leave_every_key_equal(scan_probe, old, new):
    root, original = scan_probe
    before = _keys(root)
    edited = original.replace(old, new, 1)
    assert edited != original  # the edit applied
    _edit_scan(root, edited)
    assert _keys(root) == before


@pytest.mark.parametrize(
    "edit",
    [
        pytest.param(lambda t: t.replace("_PROBE_LIMIT = 2", "_PROBE_LIMIT = 3"), id="constant"),
        pytest.param(lambda t: t.replace("return a + b", "return a - b"), id="operator"),
        pytest.param(lambda t: t.replace("return a + b", "return b + a"), id="operands"),
    ],
)  # fmt: skip
def test_a_constant_or_an_operator_moves_the_keys_of_the_stages_holding_the_module(
    scan_probe, edit
):
    root, original = scan_probe
    before = _keys(root)
    edited = edit(original)
    assert edited != original
    _edit_scan(root, edited)
    after = _keys(root)
    expected = {
        n for n, spec in STAGES.items()
        if "tumor3d.imaging.scan" in module_closure((spec.adapter_module,), str(root))
    }  # fmt: skip
    assert expected
    assert {n for n in STAGES if before[n] != after[n]} == expected


def test_a_function_left_with_only_its_docstring_digests_as_pass():
    import ast

    from tumor3d.tasks.caching import syntax_dump

    doc = syntax_dump(ast.parse('def f():\n    """Nothing."""\n'))
    assert doc == syntax_dump(ast.parse("def f():\n    pass\n"))
    assert doc != syntax_dump(ast.parse("def f():\n    return 1\n"))
    # a string statement that is not the first one is code, not a docstring
    assert syntax_dump(ast.parse('def f():\n    x = 1\n    "s"\n')) != syntax_dump(
        ast.parse("def f():\n    x = 1\n")
    )


@pytest.mark.parametrize("module", sorted(FORMAT_MODULES))
def test_store_codecs_enter_keys_through_the_format_version_only(package_copy, module, monkeypatch):
    before = _keys(package_copy)
    f = _module_file(module, package_copy)
    f.write_text(f.read_text() + _BEHAVIOUR_EDIT)  # a code change, not only a comment
    assert _keys(package_copy) == before
    import tumor3d.tasks.caching as caching

    monkeypatch.setattr(caching, "ARTIFACT_FORMAT_VERSION", "999")
    bumped = _keys(package_copy)
    assert all(bumped[n] != before[n] for n in STAGES)


def test_closure_is_computed_once_per_process():
    module_closure.cache_clear()
    module_closure(("tumor3d.tasks.measure",))
    module_closure(("tumor3d.tasks.measure",))
    assert module_closure.cache_info().hits >= 1


# -- the composable policies ---------------------------------------------------


def test_key_is_deterministic_and_ignores_store_location():
    inputs = {"mesh": _ref("a"), "config": SimplifyConfig(), "store_root": "/tmp/one"}
    assert _key("simplify-mesh", inputs) == _key(
        "simplify-mesh", {**inputs, "store_root": "/elsewhere"}
    )


def test_key_changes_with_config_input_digest_and_stage():
    base = {"mesh": _ref("a"), "config": SimplifyConfig(), "store_root": "/s"}
    k = _key("simplify-mesh", base)
    assert _key("simplify-mesh", {**base, "config": SimplifyConfig(reduction_percent=40)}) != k
    assert _key("simplify-mesh", {**base, "mesh": _ref("b")}) != k
    assert _key("render-views", base) != k


def test_each_policy_sees_only_its_part():
    base = {"mesh": _ref("a"), "config": SimplifyConfig(), "store_root": "/s"}
    other_cfg = {**base, "config": SimplifyConfig(reduction_percent=40)}
    other_mesh = {**base, "mesh": _ref("b")}
    code = StageCode(stage="simplify-mesh", modules=MODULES)
    cfg, art = StageConfig(), InputArtifacts()
    assert code.compute_key(None, base, {}) == code.compute_key(None, other_cfg, {})
    assert cfg.compute_key(None, base, {}) != cfg.compute_key(None, other_cfg, {})
    assert cfg.compute_key(None, base, {}) == cfg.compute_key(None, other_mesh, {})
    assert art.compute_key(None, base, {}) != art.compute_key(None, other_mesh, {})
    assert art.compute_key(None, base, {}) == art.compute_key(None, other_cfg, {})
    assert cfg.compute_key(None, {"mesh": _ref("a")}, {}) is None  # a stage without config


def test_artifact_identity_is_its_digest_not_its_path():
    assert fingerprint(_ref("c", ".ply")) == fingerprint(_ref("c", ".nii.gz"))


def test_input_source_location_is_not_part_of_the_key():
    a = InputSource(path="/data/a/flair.nii.gz", name="flair.nii.gz", digest="d" * 64,
                    modality="flair", patient_id="p1")  # fmt: skip
    b = a.model_copy(update={"path": "/moved/flair.nii.gz"})
    c = a.model_copy(update={"digest": "e" * 64})
    mods = ("tumor3d.tasks.ingest",)
    assert _key("ingest-scan", {"source": a}, mods) == _key("ingest-scan", {"source": b}, mods)
    assert _key("ingest-scan", {"source": a}, mods) != _key("ingest-scan", {"source": c}, mods)


def test_input_source_patient_id_is_not_part_of_the_key_but_its_content_is():
    # issue 29: the same file under another id is the same computation
    a = InputSource(path="/data/a/flair.nii.gz", name="flair.nii.gz", digest="d" * 64,
                    modality="flair", patient_id="p1")  # fmt: skip
    mods = ("tumor3d.tasks.ingest",)
    key = _key("ingest-scan", {"source": a}, mods)
    same = a.model_copy(update={"patient_id": "p2", "id_derived": True})
    assert _key("ingest-scan", {"source": same}, mods) == key
    for change in ({"modality": "t2"}, {"name": "other.nii.gz"}, {"slice_gap_mm": 1.0},
                   {"series_uid": "1.2.3"}, {"skip_unreadable": True}):  # fmt: skip
        assert _key("ingest-scan", {"source": a.model_copy(update=change)}, mods) != key, change


def test_arrays_cannot_sneak_into_keys():
    with pytest.raises(TypeError, match="ndarray"):
        fingerprint(np.zeros(3))


def test_every_stage_task_uses_the_single_policy_factory():
    inputs = {"mesh": _ref("a"), "config": SimplifyConfig(), "store_root": "/s"}
    for name, spec in STAGES.items():
        expected = _key(name, inputs, (spec.adapter_module,))
        assert spec.task.cache_policy.compute_key(None, inputs, {}) == expected, name


def test_code_digests_parse_under_one_lock_and_agree_across_threads(package_copy, monkeypatch):
    # ast.parse is not thread-safe on CPython 3.11 (python/cpython#106905: a cohort's
    # lanes publishing at once failed with "AST constructor recursion depth mismatch");
    # every parse of the closure walk must hold the module's lock
    import ast
    from concurrent.futures import ThreadPoolExecutor

    import tumor3d.tasks.caching as caching

    real_parse = ast.parse
    unlocked = []

    def checked(*args, **kwargs):
        if not caching._AST_LOCK.locked():
            unlocked.append(kwargs.get("filename"))
        return real_parse(*args, **kwargs)

    monkeypatch.setattr(caching.ast, "parse", checked)
    caching._source_facts.cache_clear()
    caching._parse_module.cache_clear()
    module_closure.cache_clear()
    code_digest.cache_clear()
    roots = [(spec.adapter_module,) for spec in STAGES.values()]
    with ThreadPoolExecutor(max_workers=4) as pool:
        digests = list(pool.map(lambda r: code_digest(r, str(package_copy)), roots * 2))
    caching._source_facts.cache_clear()
    caching._parse_module.cache_clear()
    assert unlocked == []
    assert digests[: len(roots)] == digests[len(roots) :]  # the same closure, the same key


def test_a_retrained_shipped_model_changes_exactly_the_segment_key(package_copy):
    """The learned models are data, not modules: their bytes enter the key of every stage
    whose code closure holds the module that reads them (``DATA_FILES``), the segment
    stage's among them, and no other stage's."""
    from tumor3d.tasks.caching import DATA_FILES

    before = _keys(package_copy)
    model = package_copy / DATA_FILES["tumor3d.learned.shipped"][0]
    assert model.is_file()
    model.write_bytes(model.read_bytes() + b"\0")
    after = _keys(package_copy)
    expected = {
        n for n, spec in STAGES.items()
        if "tumor3d.learned.shipped" in module_closure((spec.adapter_module,), str(package_copy))
    }  # fmt: skip
    assert "segment-tumor" in expected
    assert {n for n in STAGES if before[n] != after[n]} == expected


# -- package versions in the keys (issue 31) ------------------------------------


def _bumped(distribution: str):
    """A stand-in for ``versions()`` reporting another version of ``distribution``."""
    from tumor3d.storage.versions import versions

    real = versions()
    assert distribution in real, f"{distribution} is not among the recorded packages"
    return lambda: {**real, distribution: real[distribution] + ".post999"}


def _stage_keys() -> dict[str, str]:
    inputs = {"mesh": _ref("a"), "config": SimplifyConfig(), "store_root": "/s"}
    return {n: _key(n, inputs, (spec.adapter_module,)) for n, spec in STAGES.items()}


@pytest.mark.parametrize("distribution", ["scikit-image", "numpy", "numba", "open3d-cpu"])
def test_a_numerical_package_upgrade_moves_the_keys_of_the_stages_importing_it(
    monkeypatch, distribution
):
    import tumor3d.tasks.caching as caching

    before = _stage_keys()
    assert _stage_keys() == before  # the same versions, the same keys
    monkeypatch.setattr(caching, "versions", _bumped(distribution))
    after = _stage_keys()
    expected = {
        n for n, spec in STAGES.items()
        if distribution in caching.closure_packages((spec.adapter_module,))
    }  # fmt: skip
    assert expected, f"no stage imports {distribution}?"
    assert {n for n in STAGES if before[n] != after[n]} == expected


@pytest.mark.parametrize("distribution", ["prefect", "pydantic", "matplotlib"])
def test_an_upgrade_of_a_package_that_computes_nothing_keeps_every_key(monkeypatch, distribution):
    import tumor3d.tasks.caching as caching

    before = _stage_keys()
    monkeypatch.setattr(caching, "versions", _bumped(distribution))
    assert _stage_keys() == before


def test_only_the_packages_a_closure_imports_enter_its_key(package_copy, monkeypatch):
    import tumor3d.tasks.caching as caching

    (package_copy / "tasks" / "probe_adapter.py").write_text(
        "import numpy as np\n\n\ndef run(x):\n    from skimage import measure\n\n"
        "    return measure.label(np.asarray(x))\n"
    )
    roots = ("tumor3d.tasks.probe_adapter",)
    root = str(package_copy)
    assert caching.closure_packages(roots, root) == ("numpy", "scikit-image")

    def key():
        return StageCode(stage="probe", modules=roots, root=root).compute_key(None, {}, {})

    before = key()
    monkeypatch.setattr(caching, "versions", _bumped("scipy"))  # not imported: same key
    assert key() == before
    monkeypatch.setattr(caching, "versions", _bumped("scikit-image"))  # imported in a function
    assert key() != before


def test_one_versions_function_for_keys_provenance_publish_key_and_reports():
    import tumor3d.storage.evaluation_report
    import tumor3d.storage.provenance
    import tumor3d.storage.versions
    import tumor3d.tasks.caching
    import tumor3d.tasks.publish

    one = tumor3d.storage.versions.versions
    assert tumor3d.tasks.caching.versions is one
    assert tumor3d.storage.provenance.versions is one
    assert tumor3d.tasks.publish.versions is one  # the publish key
    assert tumor3d.storage.evaluation_report.versions is one
    recorded = one()
    numerical = tumor3d.storage.versions.NUMERICAL_PACKAGES
    every_key_package = {d for dists in numerical.values() for d in dists}
    assert every_key_package <= set(recorded)  # provenance records what the keys hold
    assert {"tumor3d", "python", "platform"} <= set(recorded)
