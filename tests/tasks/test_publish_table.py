"""The table of published files (tumor3d.storage.derivatives), the docs and the BIDS layout."""

from __future__ import annotations

import re
from pathlib import Path

from tumor3d.storage import derivatives
from tumor3d.storage.derivatives import DERIVATIVES, bids_names

ROOT = Path(__file__).resolve().parents[2]


def _declared_files() -> set[str]:
    names = {d.name for d in DERIVATIVES if not d.is_family}
    family = [d for d in DERIVATIVES if d.is_family]
    assert len(family) == 1  # the renders
    return names | {f"{p}{s}" for p, s in derivatives._family_files()}


def _readme_output_files() -> set[str]:
    """The file names in the first column of README's table of a patient's outputs."""
    text = (ROOT / "README.md").read_text()
    start = text.index("| file | content |")
    table = text[start : text.index("\n\n", start)]
    first = [line.split("|")[1] for line in table.splitlines()[2:]]
    return {n for cell in first for n in re.findall(r"`([^`]+)`", cell)}


def test_the_readme_outputs_table_lists_exactly_the_declared_files():
    readme = _readme_output_files()
    # the README names the renders one by one (not the sagittal cut-away, off by default),
    # the table as a family
    declared = _declared_files()
    assert readme - declared == set(), "in README, not declared"
    missing = declared - readme - {"render_cut_sagittal.png"}
    assert missing == set(), "declared, not in README's outputs table"


def test_every_declared_file_has_its_sources_description_and_an_encoder_in_storage():
    for d in DERIVATIVES:
        assert d.sources and d.description, d.name
        assert d.encode.__module__.startswith("tumor3d.storage."), d.name
    names = [d.name for d in DERIVATIVES]
    assert len(names) == len(set(names))
    assert names[-1] == "report.html"  # it links the others: written last


def test_bids_names_come_from_the_table_and_never_collide():
    names = bids_names("01")
    assert set(names) == _declared_files() - {
        "viewer.html", "slices.parquet", "metrics.parquet", "provenance.json", "report.html",
    }  # fmt: skip
    assert len(set(names.values())) == len(names)
    # independent expectation: the paths BIDS users were given (README, sMRIPrep's naming)
    assert names["tumor_mask.nii.gz"] == "anat/sub-01_desc-tumor_mask.nii.gz"
    assert names["tumor_probability.nii.gz"] == "anat/sub-01_label-tumor_probseg.nii.gz"
    assert names["render_turntable.gif"] == "figures/sub-01_desc-turntable_render.gif"
    assert names["tumor_simplified.stl"] == "anat/sub-01_desc-lpssimplified_tumor.stl"


def test_the_readme_names_every_declared_metrics_column():
    from tumor3d.tasks.stages import STAGES

    text = (ROOT / "README.md").read_text()
    row = next(line for line in text.splitlines() if line.startswith("| `metrics.parquet` |"))
    declared = [col for spec in STAGES.values() if isinstance(spec.metrics, dict)
                for col in spec.metrics]  # fmt: skip
    assert declared  # the stages declare columns
    assert [c for c in declared if f"`{c}`" not in row] == []
