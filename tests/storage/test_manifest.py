"""Tests of tumor3d.storage.manifest: cohort CSV reading, validation and writing."""

from __future__ import annotations

from pathlib import Path

import pytest

from tumor3d.errors import InputError
from tumor3d.storage.manifest import ManifestRow, read_manifest, read_manifest_rows, write_manifest

HEADER = "patient_id,image,modality,reference,reference_labels,slice_thickness_mm,slice_gap_mm\n"


@pytest.fixture
def cohort(tmp_path):
    """A manifest folder with two inputs and a reference, in sub-folders."""
    root = tmp_path / "cohort"
    (root / "images").mkdir(parents=True)
    (root / "images" / "p1.nii.gz").write_bytes(b"x")
    (root / "images" / "p2_dicom").mkdir()
    (root / "refs").mkdir()
    (root / "refs" / "p1_seg.nii.gz").write_bytes(b"x")
    return root


def write_csv(root: Path, text: str, name: str = "manifest.csv") -> Path:
    p = root / name
    p.write_text(text, encoding="utf-8")
    return p


def test_valid_manifest_resolves_relative_paths(cohort, tmp_path):
    other = tmp_path / "elsewhere.nii"
    other.write_bytes(b"x")
    p = write_csv(
        cohort,
        HEADER
        + 'p1,images/p1.nii.gz,FLAIR,refs/p1_seg.nii.gz,"1,2,4",2,3\n'
        + "p2,./images/p2_dicom,t2,,,,\n"
        + f"p3,{other},t1c,,,2.5,\n",
    )
    rows = read_manifest(p)
    assert [r.patient_id for r in rows] == ["p1", "p2", "p3"]
    r1, r2, r3 = rows
    assert r1.image == (cohort / "images" / "p1.nii.gz").resolve()
    assert r1.image.is_absolute()
    assert r1.modality == "flair"
    assert r1.reference == (cohort / "refs" / "p1_seg.nii.gz").resolve()
    assert r1.reference_labels == (1, 2, 4)
    assert (r1.slice_thickness_mm, r1.slice_gap_mm) == (2.0, 3.0)
    assert r2.image == (cohort / "images" / "p2_dicom").resolve()
    assert r2.reference is None and r2.reference_labels is None
    assert r2.slice_thickness_mm is None and r2.slice_gap_mm is None
    assert r3.image == other.resolve() and r3.slice_thickness_mm == 2.5


def test_resolution_does_not_depend_on_the_working_directory(cohort, monkeypatch, tmp_path):
    p = write_csv(cohort, "patient_id,image,modality\np1,images/p1.nii.gz,t2\n")
    monkeypatch.chdir(tmp_path)
    assert read_manifest(p)[0].image == (cohort / "images" / "p1.nii.gz").resolve()


def test_write_then_read_round_trip_with_relative_paths(cohort):
    rows = [
        ManifestRow(
            "p1",
            cohort / "images" / "p1.nii.gz",
            "flair",
            reference=cohort / "refs" / "p1_seg.nii.gz",
            reference_labels=(1, 2, 3, 4),
            slice_thickness_mm=2.0,
            slice_gap_mm=3.0,
        ),
        ManifestRow("p2", cohort / "images" / "p2_dicom", "t2"),
    ]
    out = write_manifest(rows, cohort / "out.csv")
    text = out.read_text()
    assert "images/p1.nii.gz" in text and str(cohort) not in text
    assert '"1,2,3,4"' in text
    assert read_manifest(out) == rows


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (
            "patient_id,image\np1,images/p1.nii.gz\n",
            r"missing required column\(s\) modality",
        ),
        (
            "patient_id,image,modality,notes\np1,images/p1.nii.gz,t2,x\n",
            r"unknown column\(s\) 'notes'",
        ),
        ("patient_id,image,modality\n", r"no data rows below the header"),
        (  # a spreadsheet's export (a user audit): the delimiter named
            "patient_id;image;modality\np1;images/p1.nii.gz;t2\n",
            r"missing required column\(s\) patient_id, image, modality in the header \(found: "
            r"patient_id;image;modality\) \(the manifest must be comma-separated\)",
        ),
    ],
)
def test_bad_header(cohort, text, match):
    with pytest.raises(InputError, match=rf"manifest\.csv: {match}"):
        read_manifest(write_csv(cohort, text))


# one invalid data row per case; the bad row is data row 2 (line 3)
GOOD = "p0,images/p1.nii.gz,t2,,,,\n"


@pytest.mark.parametrize(
    ("row", "column", "problem"),
    [
        (",images/p1.nii.gz,t2,,,,", "patient_id", r"empty value"),
        ("p1,,t2,,,,", "image", r"empty value"),
        ("p1,images/p1.nii.gz,,,,,", "modality", r"empty value"),
        ("../evil,images/p1.nii.gz,t2,,,,", "patient_id", r"unsafe patient id '\.\./evil'"),
        (
            "p0,images/p1.nii.gz,t2,,,,",
            "patient_id",
            r"duplicate patient_id 'p0' \(also in data row 1\)",
        ),
        ("p1,images/p1.nii.gz,pd,,,,", "modality", r"unknown modality 'pd'"),
        ("p1,images/p1.nii.gz,t2,,,two,", "slice_thickness_mm", r"'two' is not a number"),
        ("p1,images/p1.nii.gz,t2,,,-2,", "slice_thickness_mm", r"'-2' must be a positive number"),
        ("p1,images/p1.nii.gz,t2,,,2,-1", "slice_gap_mm", r"'-1' must be a non-negative number"),
        (
            'p1,images/p1.nii.gz,t2,refs/p1_seg.nii.gz,"1,x",,',
            "reference_labels",
            r"bad label list '1,x'",
        ),
        (
            'p1,images/p1.nii.gz,t2,refs/p1_seg.nii.gz,"0,1",,',
            "reference_labels",
            r"bad label list '0,1'",
        ),
        (
            "p1,images/p1.nii.gz,t2,,2,,",
            "reference_labels",
            r"label values given without a reference",
        ),
        ("p1,images/missing.nii.gz,t2,,,,", "image", r".*missing\.nii\.gz does not exist"),
        (
            "p1,images/p1.nii.gz,t2,refs/none.nii.gz,,,",
            "reference",
            r".*none\.nii\.gz does not exist",
        ),
        (
            "p1,images/p1.nii.gz,t2,,,,,extra",
            r"\(extra\)",
            r"the row has more values than the 7 columns",
        ),
    ],
)
def test_invalid_row_named_by_row_and_column(cohort, row, column, problem):
    p = write_csv(cohort, HEADER + GOOD + row + "\n")
    with pytest.raises(
        InputError, match=rf"manifest\.csv: data row 2 \(line 3\), column '{column}': {problem}"
    ):
        read_manifest(p)


def test_missing_manifest(tmp_path):
    with pytest.raises(InputError, match=r"nope\.csv: no such manifest file"):
        read_manifest(tmp_path / "nope.csv")


def test_write_rejects_duplicate_ids(cohort):
    row = ManifestRow("p1", cohort / "images" / "p1.nii.gz", "t2")
    with pytest.raises(InputError, match=r"duplicate patient_id p1"):
        write_manifest([row, row], cohort / "dup.csv")
    assert not (cohort / "dup.csv").exists()


# --------------------------------------------------------------------------- evaluation columns

EVAL_HEADER = (
    "patient_id,image,modality,reference,reference_labels,emulate_step_mm,"
    "emulate_thickness_mm,reference_kind\n"
)


def test_emulation_and_reference_kind_columns_round_trip(cohort):
    p = write_csv(
        cohort,
        EVAL_HEADER
        + 'p1,images/p1.nii.gz,flair,refs/p1_seg.nii.gz,"1,2,3,4",5,2,expert\n'
        + "p2,images/p1.nii.gz,t2,,,5,,tumor-free\n",
    )
    r1, r2 = read_manifest(p)
    assert (r1.emulate_step_mm, r1.emulate_thickness_mm, r1.reference_kind) == (5.0, 2.0, "expert")
    assert (r2.emulate_step_mm, r2.emulate_thickness_mm) == (5.0, None)
    assert r2.reference_kind == "tumor_free"
    again = read_manifest(write_manifest([r1, r2], cohort / "again.csv"))
    assert again == [r1, r2]


@pytest.mark.parametrize(
    ("row", "column", "problem"),
    [
        ("p1,images/p1.nii.gz,t2,,,,2,", "emulate_thickness_mm", "given without emulate_step_mm"),
        ("p1,images/p1.nii.gz,t2,,,5,6,", "emulate_thickness_mm", "6 mm exceeds emulate_step_mm"),
        ("p1,images/p1.nii.gz,t2,,,0,,", "emulate_step_mm", "'0' must be a positive number"),
        ("p1,images/p1.nii.gz,t2,,,,,guess", "reference_kind", "unknown kind 'guess'"),
        (
            "p1,images/p1.nii.gz,t2,refs/p1_seg.nii.gz,,,,tumor_free",
            "reference_kind",
            "tumor_free, but a reference file is given",
        ),
    ],
)
def test_invalid_evaluation_columns(cohort, row, column, problem):
    p = write_csv(cohort, EVAL_HEADER + "p0,images/p1.nii.gz,t2,,,,,\n" + row + "\n")
    with pytest.raises(
        InputError, match=rf"manifest\.csv: data row 2 \(line 3\), column '{column}': {problem}"
    ):
        read_manifest(p)


def test_lenient_read_keeps_good_rows_and_names_each_bad_one(cohort):
    p = write_csv(
        cohort,
        HEADER
        + "p1,images/p1.nii.gz,t2,,,,\n"
        + "p2,images/absent.nii.gz,t2,,,,\n"
        + "p1,images/p1.nii.gz,t2,,,,\n"
        + "p3,images/p1.nii.gz,t2,refs/absent_seg.nii.gz,,,\n"
        + "p4,images/p1.nii.gz,t2,,,,\n",
    )
    rows, problems = read_manifest_rows(p)
    assert [r.patient_id for r in rows] == ["p1", "p4"]
    assert [(q.row, q.patient_id, q.column, q.missing_file) for q in problems] == [
        (2, "p2", "image", True),
        (3, "p1", "patient_id", False),
        (4, "p3", "reference", True),
    ]
    assert "data row 3 (line 4)" in problems[1].message and "duplicate" in problems[1].message
    with pytest.raises(InputError, match="data row 2"):
        read_manifest(p)  # strict: the first bad row stops it


def test_data_dir_variable_in_paths(cohort, monkeypatch, tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    (data / "x.nii.gz").write_bytes(b"x")
    p = write_csv(cohort, "patient_id,image,modality\np1,${TUMOR3D_DATA_DIR}/x.nii.gz,t2\n")
    monkeypatch.setenv("TUMOR3D_DATA_DIR", str(data))
    assert read_manifest(p)[0].image == (data / "x.nii.gz").resolve()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("TUMOR3D_DATA_DIR", "data")  # relative: to the working directory
    assert read_manifest(p)[0].image == (data / "x.nii.gz").resolve()
    monkeypatch.delenv("TUMOR3D_DATA_DIR")
    rows, problems = read_manifest_rows(p)  # default ../shared/data: absent here, or present
    assert len(rows) + len(problems) == 1


def test_an_unset_variable_in_a_path_is_named_as_such(cohort, monkeypatch, tmp_path):
    """A user audit: ``${NOPE_VAR}/flair.nii.gz`` was read as a relative path and failed
    later as "no such file"; it is an invalid row (a cohort refuses it before any work)."""
    monkeypatch.delenv("NOPE_VAR", raising=False)
    p = write_csv(cohort, "patient_id,image,modality\np1,${NOPE_VAR}/flair.nii.gz,t2\n")
    said = r"data row 1 .*'image': environment variable \$NOPE_VAR is not set \(in '\$\{NOPE"
    with pytest.raises(InputError, match=said):
        read_manifest(p, require_files=False)
    monkeypatch.setenv("NOPE_VAR", str(tmp_path))
    assert read_manifest(p, require_files=False)[0].image == (tmp_path / "flair.nii.gz").resolve()


def test_missing_image_is_kept_for_a_cohort_but_other_problems_are_not(cohort):
    """Issue 12/6: a cohort row whose image is absent fails alone; the manifest is not invalid."""
    p = write_csv(
        cohort,
        "patient_id,image,modality\np1,images/p1.nii.gz,t2\nghost,images/ghost.nii.gz,t2\n",
    )
    with pytest.raises(InputError, match=r"data row 2 .*'image': .*ghost\.nii\.gz does not exist"):
        read_manifest(p)  # the default (evaluate, python callers): an error
    rows = read_manifest(p, require_files=False)
    assert [r.patient_id for r in rows] == ["p1", "ghost"]
    assert rows[1].image == (cohort / "images" / "ghost.nii.gz").resolve()
    assert not rows[1].image.exists()
    # every other column is still validated
    bad = write_csv(cohort, "patient_id,image,modality\nghost,images/ghost.nii.gz,x-ray\n", "b.csv")
    with pytest.raises(InputError, match=r"unknown modality 'x-ray'"):
        read_manifest(bad, require_files=False)


def test_brain_mask_column_resolves_like_image_and_round_trips(cohort, monkeypatch, tmp_path):
    """Issue 7: optional brain_mask, relative to the manifest or through ${VAR}."""
    (cohort / "masks").mkdir()
    (cohort / "masks" / "p1_brain.nii.gz").write_bytes(b"x")
    elsewhere = tmp_path / "vault"
    elsewhere.mkdir()
    (elsewhere / "p2_brain.nii.gz").write_bytes(b"x")
    monkeypatch.setenv("MASK_VAULT", str(elsewhere))
    p = write_csv(
        cohort,
        "patient_id,image,modality,brain_mask\n"
        "p1,images/p1.nii.gz,t2,masks/p1_brain.nii.gz\n"
        "p2,images/p1.nii.gz,t2,${MASK_VAULT}/p2_brain.nii.gz\n"
        "p3,images/p1.nii.gz,t2,\n",
    )
    r1, r2, r3 = read_manifest(p)
    assert r1.brain_mask == (cohort / "masks" / "p1_brain.nii.gz").resolve()
    assert r2.brain_mask == (elsewhere / "p2_brain.nii.gz").resolve()
    assert r3.brain_mask is None
    out = write_manifest([r1, r2, r3], cohort / "again.csv")
    assert "masks/p1_brain.nii.gz" in out.read_text()
    assert read_manifest(out) == [r1, r2, r3]


def test_absent_brain_mask_is_a_missing_file_of_that_row(cohort):
    p = write_csv(
        cohort,
        "patient_id,image,modality,brain_mask\n"
        "p1,images/p1.nii.gz,t2,masks/none.nii.gz\n"
        "p2,images/p1.nii.gz,t2,\n",
    )
    rows, problems = read_manifest_rows(p)
    assert [r.patient_id for r in rows] == ["p2"]
    assert [(q.row, q.column, q.missing_file) for q in problems] == [(1, "brain_mask", True)]
    assert "none.nii.gz does not exist" in problems[0].message
    kept = read_manifest(p, require_files=False)  # a cohort: that row fails alone when run
    assert kept[0].brain_mask == (cohort / "masks" / "none.nii.gz").resolve()


def test_segmentation_column_resolves_like_brain_mask_and_round_trips(cohort, tmp_path):
    """Issue 33: optional segmentation, relative to the manifest; absent = a missing file."""
    (cohort / "masks").mkdir()
    (cohort / "masks" / "p1_seg.nii.gz").write_bytes(b"x")
    p = write_csv(
        cohort,
        "patient_id,image,modality,segmentation\n"
        "p1,images/p1.nii.gz,t2,masks/p1_seg.nii.gz\n"
        "p2,images/p1.nii.gz,t2,\n"
        "p3,images/p1.nii.gz,t2,masks/none.nii.gz\n",
    )
    rows, problems = read_manifest_rows(p)
    assert [r.patient_id for r in rows] == ["p1", "p2"]
    assert rows[0].segmentation == (cohort / "masks" / "p1_seg.nii.gz").resolve()
    assert rows[1].segmentation is None
    assert [(q.row, q.column, q.missing_file) for q in problems] == [(3, "segmentation", True)]
    out = write_manifest(rows, cohort / "again.csv")
    assert "masks/p1_seg.nii.gz" in out.read_text()
    assert read_manifest(out) == rows
    emulated = write_csv(
        cohort,
        "patient_id,image,modality,segmentation,emulate_step_mm\n"
        "p1,images/p1.nii.gz,t2,masks/p1_seg.nii.gz,5\n",
        "emulated.csv",
    )
    with pytest.raises(InputError, match=r"column 'segmentation': given with emulate_step_mm"):
        read_manifest(emulated)
