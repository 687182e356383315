"""The publish key's code digest: syntax trees, codecs included (issue 31).

It was the raw bytes of the publishing modules (a comment republished every
patient) computed by a second copy of the module lookup; it is now
:func:`tumor3d.tasks.caching.code_digest` with ``include_codecs=True``. Checked on a
copy of the project, edited.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from tumor3d.package_layout import SOURCE_FOLDERS
from tumor3d.tasks.caching import FORMAT_MODULES, code_digest

ROOT = Path(__file__).resolve().parents[2]
ROOTS = ("tumor3d.tasks.publish", "tumor3d.storage.derivatives")


def _copy(tmp_path: Path) -> Path:
    for pkg in SOURCE_FOLDERS:  # tumor3d/ and the folders mapped into it
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    return tmp_path


def test_a_codec_counts_for_publishing_by_its_behaviour_only(tmp_path):
    root = str(_copy(tmp_path))
    codec = "tumor3d.storage.formats"
    assert codec in FORMAT_MODULES
    path = tmp_path / "storage" / "formats.py"
    before = code_digest(ROOTS, root, include_codecs=True)
    stage_like = code_digest(ROOTS, root)
    path.write_text(path.read_text() + "\n# a comment\n\n")
    code_digest.cache_clear()
    assert code_digest(ROOTS, root, include_codecs=True) == before  # a comment: same key
    path.write_text(path.read_text() + "\n_PUBLISH_TEST_CONSTANT = 1\n")
    code_digest.cache_clear()
    assert code_digest(ROOTS, root, include_codecs=True) != before  # code: republish
    assert code_digest(ROOTS, root) == stage_like  # a stage key ignores codecs (format version)


def test_the_publisher_digest_is_the_code_digest_of_the_table_encoders():
    from tumor3d.storage.derivatives import encoder_modules
    from tumor3d.tasks.publish import publisher_code_digest

    assert publisher_code_digest() == code_digest(
        ("tumor3d.tasks.publish", *encoder_modules()), include_codecs=True
    )


def test_the_publisher_closure_holds_every_module_that_writes_a_published_file():
    from tumor3d.storage.derivatives import encoder_modules
    from tumor3d.tasks.caching import module_closure

    closure = set(module_closure(("tumor3d.tasks.publish", *encoder_modules())))
    # independent expectation: the modules the publisher was written with (the former
    # hand-kept list) and those the table's encoders call
    writers = {
        "tumor3d.storage.bids", "tumor3d.storage.formats", "tumor3d.storage.nifti",
        "tumor3d.storage.patient_outputs", "tumor3d.storage.provenance",
        "tumor3d.storage.publish", "tumor3d.storage.slice_table", "tumor3d.segmentation.review",
        "tumor3d.storage.viewer", "tumor3d.storage.report_html", "tumor3d.storage.derivatives",
        "tumor3d.storage.remote_publish", "tumor3d.visual.overlay",
    }  # fmt: skip
    assert writers <= closure, sorted(writers - closure)
    assert "tumor3d.flows.patient" not in closure  # the flow's wiring republishes nothing


def test_an_encoder_edit_republishes_and_a_comment_does_not(tmp_path):
    root = str(_copy(tmp_path))
    path = tmp_path / "storage" / "derivatives.py"
    before = code_digest(ROOTS, root, include_codecs=True)
    commented = path.read_text().replace("\n\ndef _viewer(", "\n\n# the viewer\ndef _viewer(", 1)
    assert "# the viewer" in commented
    path.write_text(commented)
    code_digest.cache_clear()
    assert code_digest(ROOTS, root, include_codecs=True) == before
    text = path.read_text()
    edited = text.replace('space="LPS"', 'space="RAS"', 1)
    assert edited != text
    path.write_text(edited)
    code_digest.cache_clear()
    assert code_digest(ROOTS, root, include_codecs=True) != before
