"""The publish key's code digest: syntax trees, codecs included (issue 31).

It was the raw bytes of the publishing modules (a comment republished every
patient) computed by a second copy of the module lookup; it is now
:func:`tumor3d.tasks.caching.code_digest` with ``include_codecs=True``. Checked on a
copy of the project, edited.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from tumor3d.tasks.caching import FORMAT_MODULES, code_digest

ROOT = Path(__file__).resolve().parents[2]
ROOTS = ("tumor3d.flows.patient", "tumor3d.storage.patient_outputs")


def _copy(tmp_path: Path) -> Path:
    for pkg in ("tumor3d",):
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    return tmp_path


def test_a_codec_counts_for_publishing_by_its_behaviour_only(tmp_path):
    root = str(_copy(tmp_path))
    codec = "tumor3d.storage.formats"
    assert codec in FORMAT_MODULES
    path = tmp_path / "tumor3d" / "storage" / "formats.py"
    before = code_digest(ROOTS, root, include_codecs=True)
    stage_like = code_digest(ROOTS, root)
    path.write_text(path.read_text() + "\n# a comment\n\n")
    code_digest.cache_clear()
    assert code_digest(ROOTS, root, include_codecs=True) == before  # a comment: same key
    path.write_text(path.read_text() + "\n_PUBLISH_TEST_CONSTANT = 1\n")
    code_digest.cache_clear()
    assert code_digest(ROOTS, root, include_codecs=True) != before  # code: republish
    assert code_digest(ROOTS, root) == stage_like  # a stage key ignores codecs (format version)


def test_the_publisher_digest_is_the_code_digest():
    from tumor3d.flows.patient import PUBLISHER_MODULES, _publisher_code_digest

    assert _publisher_code_digest() == code_digest(
        ("tumor3d.flows.patient", *PUBLISHER_MODULES), include_codecs=True
    )
