"""The BIDS-derivatives layout of a patient's published folder (``--layout bids``).

BIDS 1.9 "Derivatives" (common data types, masks, probabilistic
segmentations) names the volumes; the other files keep tumor3d's formats
under BIDS-style names and are listed in ``.bidsignore``. A patient is
published as ``OUT/sub-<label>/`` (one folder, swapped in as a whole like
the default layout's ``OUT/<patient_id>/``)::

    OUT/dataset_description.json          DatasetType "derivative", GeneratedBy
    OUT/.bidsignore                        the non-BIDS files below
    OUT/sub-<label>/anat/
        sub-<label>_desc-tumor_mask.nii.gz + .json        interpolated tumour mask
        sub-<label>_desc-tumorslices_mask.nii.gz + .json  mask of the acquired slices
        sub-<label>_desc-brain_mask.nii.gz + .json        brain mask (skull removal)
        sub-<label>_label-tumor_probseg.nii.gz + .json    learned method's probability
        sub-<label>_tumor.surf.gii / _desc-simplified_tumor.surf.gii / _brain.surf.gii
        sub-<label>_tumor.ply ... (RAS), sub-<label>_desc-lps_tumor.vtk / .stl (LPS)
    OUT/sub-<label>/figures/               renders and overlays (as fMRIPrep's figures/)
    OUT/sub-<label>/report.html, viewer.html, provenance.json, metrics.parquet,
        slices.parquet                     as in the default layout

Names
-----
Masks are ``_desc-<what>_mask`` as sMRIPrep's ``desc-brain_mask``; the
probability is ``_label-tumor_probseg`` (BIDS puts the structure of a
probabilistic segmentation in ``label-``). Surfaces follow sMRIPrep's
``sub-<label>_hemi-L_pial.surf.gii``: the suffix names the surface (here
``tumor`` or ``brain``; a tumour has no hemisphere), ``desc-`` the variant,
and GIFTI (``.surf.gii``, RAS millimetres, the format BIDS apps and
Connectome Workbench read) is written beside the PLY. The participant label
is the patient id when it is letters and digits only, or the label of a
``sub-<label>`` prefix (``sub-01_T2w`` -> ``01``); any other id is refused
(:func:`participant_label`), never altered: two ids must never fold onto one
label.

Sidecars: ``Type`` (``Lesion``/``Brain``, BIDS's reserved mask types),
``Description``, ``Sources`` (BIDS URIs: ``bids::`` for a file of this
dataset, ``bids:raw:`` for the input when it lies in a BIDS dataset, which
``DatasetLinks`` then names; BIDS 1.9 deprecates ``RawSources`` for this),
and on the tumour masks the volumes in mm3 and mL with each method's
definition.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import uuid
from collections.abc import Iterable, Mapping
from importlib.metadata import PackageNotFoundError, metadata
from pathlib import Path
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.storage import derivatives

__all__ = [
    "BIDSIGNORE",
    "BIDS_FILE_NAME",
    "BIDS_VERSION",
    "LAYOUTS",
    "bids_names",
    "check_dataset_root",
    "check_layout",
    "dataset_description",
    "encode_gifti_surface",
    "folder_name",
    "participant_label",
    "raw_source",
    "relayout",
    "write_dataset_files",
]

#: The BIDS version the layout follows.
BIDS_VERSION = "1.9.0"

#: ``--layout`` values: tumor3d's own folder, or BIDS derivatives.
LAYOUTS = ("default", "bids")

#: BIDS file names of this layout: entities in the specification's order
#: (``sub``, ``hemi``, ``space``, ``label``, ``desc``), then ``_<suffix>`` and the
#: extension; labels are letters and digits only.
BIDS_FILE_NAME = re.compile(
    r"^sub-(?P<sub>[A-Za-z0-9]+)"
    r"(?:_hemi-(?P<hemi>L|R))?"
    r"(?:_space-(?P<space>[A-Za-z0-9]+))?"
    r"(?:_label-(?P<label>[A-Za-z0-9]+))?"
    r"(?:_desc-(?P<desc>[A-Za-z0-9]+))?"
    r"_(?P<suffix>[A-Za-z0-9]+)"
    r"(?P<extension>\.[a-z0-9]+(?:\.[a-z0-9]+)?)$"
)

#: The files of this layout that BIDS does not define (``.bidsignore`` syntax).
BIDSIGNORE = (
    "# tumor3d files that BIDS does not define\n"
    "*/figures/\n*/report.html\n*/viewer*.html\n*/provenance.json\n*.parquet\n"
    "*.ply\n*.stl\n*.vtk\n*.surf.gii\ncohort.*\n_assets/\n"
)

_LABEL = re.compile(r"^[A-Za-z0-9]+$")
_SUB_PREFIX = re.compile(r"^sub-([A-Za-z0-9]+)(?:_.*)?$")

#: What each mask is (sidecar ``Type`` and ``Description``; its BIDS name: the derivatives table).
_MASKS: dict[str, tuple[str, str]] = {
    # default name: (Type, Description)
    "tumor_mask.nii.gz": (
        "Lesion",
        "tumour mask interpolated between the acquired slices (interpolate-slices stage), "
        "on the interpolated grid: the input's in-plane grid and orientation, with slices "
        "added between the acquired ones (its affine says where)",
    ),
    "tumor_mask_slices.nii.gz": (
        "Lesion",
        "tumour segmented on each acquired slice (segment-tumor stage), on the input's voxel grid",
    ),
    "brain_mask.nii.gz": (
        "Brain",
        "brain mask of skull removal (preprocess stage), or the mask given with --brain-mask",
    ),
    "tumor_probability.nii.gz": (
        "",
        "the learned segmentation's tumour probability (0-1), on the input's voxel grid",
    ),
}


def check_layout(layout: str) -> str:
    """``layout`` if it is one of :data:`LAYOUTS`, else a one-line :class:`InputError`."""
    if layout not in LAYOUTS:
        raise InputError(f"--layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    return layout


def participant_label(patient_id: str) -> str:
    """The BIDS participant label of a patient id (letters and digits only).

    The id itself when it is alphanumeric, or the label of a ``sub-<label>``
    prefix (an id taken from a BIDS file name); any other id is refused
    rather than altered, so that two patients never share a label.

    Examples
    --------
    >>> participant_label("P001"), participant_label("sub-01_T2w"), participant_label("sub-7")
    ('P001', '01', '7')
    >>> participant_label("pat-01")
    Traceback (most recent call last):
    ...
    tumor3d.errors.InputError: patient id 'pat-01' is not a BIDS participant label ...
    """
    pid = str(patient_id)
    if _LABEL.match(pid):
        return pid
    m = _SUB_PREFIX.match(pid)
    if m:
        return m.group(1)
    raise InputError(
        f"patient id {pid!r} is not a BIDS participant label (letters and digits only, "
        "or sub-<label>...): give --patient-id (a manifest's patient_id) such as "
        f"{re.sub(r'[^A-Za-z0-9]', '', pid) or 'P001'!r} for --layout bids"
    )


def folder_name(patient_id: str, layout: str = "default") -> str:
    """The patient's folder under ``--out``: the id, or ``sub-<label>`` for BIDS.

    >>> folder_name("p1"), folder_name("p1", "bids")
    ('p1', 'sub-p1')
    """
    if check_layout(layout) == "bids":
        return f"sub-{participant_label(patient_id)}"
    return patient_id


def bids_names(label: str) -> dict[str, str]:
    """Default-layout file name -> path in ``sub-<label>/`` (every file this layout renames).

    Read from the table of published files (:func:`tumor3d.storage.derivatives.bids_names`).

    >>> bids_names("01")["tumor_mask.nii.gz"]
    'anat/sub-01_desc-tumor_mask.nii.gz'
    >>> bids_names("01")["render_cut_axial.png"]
    'figures/sub-01_desc-cutaxial_render.png'
    """
    return derivatives.bids_names(label)


#: GIFTI surfaces made from the PLY files (RAS): PLY name -> path in ``sub-<label>/``.
def _gifti_names(label: str) -> dict[str, str]:
    sub = f"sub-{label}"
    return {
        "tumor.ply": f"anat/{sub}_tumor.surf.gii",
        "tumor_simplified.ply": f"anat/{sub}_desc-simplified_tumor.surf.gii",
        "brain_mesh.ply": f"anat/{sub}_brain.surf.gii",
    }


def encode_gifti_surface(vertices_mm: np.ndarray, faces: np.ndarray) -> bytes:
    """A GIFTI surface (``.surf.gii``) of a triangle mesh in RAS millimetres.

    Two data arrays, as FreeSurfer's and sMRIPrep's surfaces: the vertices
    (``NIFTI_INTENT_POINTSET``, float32, scanner space ``NIFTI_XFORM_SCANNER_ANAT``)
    and the triangles (``NIFTI_INTENT_TRIANGLE``, int32). Uncompressed base64.
    """
    import nibabel as nib

    v = np.asarray(vertices_mm, dtype=np.float32)
    f = np.asarray(faces, dtype=np.int32)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise InputError(
            f"a surface needs (n, 3) vertices and (m, 3) faces, got {v.shape}, {f.shape}"
        )
    scanner = "NIFTI_XFORM_SCANNER_ANAT"  # code 1 (3 would say Talairach)
    space = nib.gifti.GiftiCoordSystem(dataspace=scanner, xformspace=scanner, xform=np.eye(4))
    points = nib.gifti.GiftiDataArray(
        v, intent="NIFTI_INTENT_POINTSET", datatype="NIFTI_TYPE_FLOAT32",
        encoding="GIFTI_ENCODING_B64BIN", coordsys=space,
    )  # fmt: skip
    triangles = nib.gifti.GiftiDataArray(
        f, intent="NIFTI_INTENT_TRIANGLE", datatype="NIFTI_TYPE_INT32",
        encoding="GIFTI_ENCODING_B64BIN", coordsys=None,
    )  # fmt: skip
    img = nib.gifti.GiftiImage(darrays=[points, triangles])
    return img.to_bytes()


def raw_source(input_path: str | Path) -> tuple[Path, str] | None:
    """The BIDS dataset holding ``input_path`` and its path inside it, if it lies in one.

    A dataset is a folder with a ``dataset_description.json`` that is not a
    derivative; the input must be a file under ``sub-<label>/``.
    """
    path = Path(input_path).expanduser().resolve()
    for folder in path.parents:
        desc = folder / "dataset_description.json"
        if desc.is_file():
            try:
                doc = json.loads(desc.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                return None
            if not isinstance(doc, dict) or doc.get("DatasetType") == "derivative":
                return None
            rel = path.relative_to(folder).as_posix()
            return (folder, rel) if rel.startswith("sub-") else None
    return None


def _generated_by() -> dict[str, str]:
    from tumor3d import __version__

    entry = {"Name": "tumor3d", "Version": str(__version__)}
    try:
        meta = metadata("tumor3d")
    except PackageNotFoundError:
        return entry
    urls = [u.split(",", 1)[-1].strip() for u in meta.get_all("Project-URL") or []]
    url = next((u for u in urls if u), None) or meta.get("Home-page")
    if url and url != "UNKNOWN":
        entry["CodeURL"] = url
    return entry


def dataset_description(raw: Path | None = None, out_dir: Path | None = None) -> dict[str, Any]:
    """``dataset_description.json`` of the derivative dataset.

    ``raw`` (a BIDS dataset an input came from) adds ``DatasetLinks`` ``raw``
    (its path relative to ``out_dir``: no absolute path of this machine is
    written) and a ``SourceDatasets`` entry (its DOI when it declares one).
    """
    doc: dict[str, Any] = {
        "Name": "tumor3d brain-tumour reconstruction",
        "BIDSVersion": BIDS_VERSION,
        "DatasetType": "derivative",
        "GeneratedBy": [_generated_by()],
    }
    if raw is not None and out_dir is not None:
        rel = os.path.relpath(raw, Path(out_dir).resolve())
        doc["DatasetLinks"] = {"raw": Path(rel).as_posix()}
        source: dict[str, str] = {"URL": "bids:raw:"}
        try:
            raw_doc = json.loads((raw / "dataset_description.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            raw_doc = {}
        if isinstance(raw_doc, dict) and raw_doc.get("DatasetDOI"):
            source["DOI"] = str(raw_doc["DatasetDOI"])
        doc["SourceDatasets"] = [source]
    return doc


def _existing_description(out_dir: Path) -> dict[str, Any] | None:
    path = out_dir / "dataset_description.json"
    if not (path.exists() or path.is_symlink()):
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        doc = None
    names = []
    if isinstance(doc, dict) and isinstance(doc.get("GeneratedBy"), list):
        names = [g.get("Name") for g in doc["GeneratedBy"] if isinstance(g, dict)]
    if path.is_symlink() or not isinstance(doc, dict) or "tumor3d" not in names:
        raise InputError(
            "this dataset_description.json is not a tumor3d derivative's (a raw BIDS dataset "
            "or another pipeline's); --layout bids would replace it: choose another --out, "
            "e.g. DATASET/derivatives/tumor3d",
            path=str(path),
        )
    return doc


def check_dataset_root(out_dir: str | Path, inputs: Iterable[str | Path] = ()) -> None:
    """Refuse a BIDS ``--out`` whose ``dataset_description.json`` is not tumor3d's.

    Checked before any work: ``OUT/dataset_description.json`` and
    ``OUT/.bidsignore`` are (re)written by every BIDS publish, so they must be
    absent or a tumor3d derivative's, and never one of ``inputs``.
    """
    out = Path(out_dir).expanduser()
    for name in ("dataset_description.json", ".bidsignore"):
        target = (out / name).resolve()
        for item in inputs:
            if Path(item).expanduser().resolve() == target:
                raise InputError(
                    f"--layout bids writes {name} in --out, which is this input: choose "
                    "another --out",
                    path=str(item),
                )
    _existing_description(out)


def _write_atomic(path: Path, text: str) -> None:
    if path.is_file() and path.read_text(encoding="utf-8") == text:
        return
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_dataset_files(out_dir: str | Path, raw: Path | None = None) -> None:
    """Write ``dataset_description.json`` and ``.bidsignore`` at the dataset root (atomic).

    An existing description keeps its ``DatasetLinks`` ``raw`` when ``raw``
    is None or names the same dataset; one of another tool is refused
    (:func:`check_dataset_root`).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    old = _existing_description(out) or {}
    doc = dataset_description(raw, out)
    if "DatasetLinks" not in doc and isinstance(old.get("DatasetLinks"), dict):
        doc["DatasetLinks"] = old["DatasetLinks"]
        if "SourceDatasets" in old:
            doc["SourceDatasets"] = old["SourceDatasets"]
    _write_atomic(out / "dataset_description.json", json.dumps(doc, indent=2) + "\n")
    _write_atomic(out / ".bidsignore", BIDSIGNORE)


def _num(metrics: Mapping[str, Any], key: str) -> float | None:
    v = metrics.get(key)
    try:
        f = float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return f if np.isfinite(f) and not isinstance(v, bool) else None


def _volumes(metrics: Mapping[str, Any], methods: Mapping[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, definition in methods.items():
        mm3 = _num(metrics, key)
        if mm3 is None:
            continue
        name = key.removeprefix("volume_").removesuffix("_mm3")
        out[name] = {"mm3": mm3, "mL": mm3 / 1000.0, "Method": definition}
    return out


def _sidecars(
    label: str,
    present: set[str],
    metrics: Mapping[str, Any],
    volume_methods: Mapping[str, str],
    raw_uri: str | None,
) -> dict[str, dict[str, Any]]:
    """Default NIfTI name -> its JSON sidecar."""
    sub = f"sub-{label}"
    raw = [raw_uri] if raw_uri else []
    slices_uri = f"bids::{sub}/anat/{sub}_desc-tumorslices_mask.nii.gz"
    sources = {
        "tumor_mask.nii.gz": [slices_uri],
        "tumor_mask_slices.nii.gz": raw,
        "brain_mask.nii.gz": raw,
        "tumor_probability.nii.gz": raw,
    }
    out: dict[str, dict[str, Any]] = {}
    for name, (kind, text) in _MASKS.items():
        if name not in present:
            continue
        doc: dict[str, Any] = {}
        if kind:
            doc["Type"] = kind
        doc["Description"] = text
        if sources[name]:
            doc["Sources"] = sources[name]
        if name in ("tumor_mask.nii.gz", "tumor_mask_slices.nii.gz"):
            for key in ("modality", "segment_method", "measured"):
                if metrics.get(key):
                    doc[{"modality": "Modality", "segment_method": "SegmentationMethod",
                         "measured": "WhatIsMeasured"}[key]] = str(metrics[key])  # fmt: skip
            doc["Volumes"] = _volumes(metrics, volume_methods)
        out[name] = doc
    return out


def relayout(
    staging: str | Path,
    label: str,
    files: Iterable[str],
    *,
    metrics: Mapping[str, Any],
    volume_methods: Mapping[str, str],
    raw_uri: str | None = None,
) -> dict[str, str]:
    """Move a staged default-layout folder's ``files`` to their BIDS paths; add sidecars and GIFTI.

    Returns default name -> path relative to the folder, for every file of
    ``files`` (one not renamed by :func:`bids_names` keeps its name), plus the
    sidecars and GIFTI surfaces written (under their own paths as keys).
    """
    from tumor3d.storage.formats import decode_ply

    folder = Path(staging)
    names = bids_names(label)
    present = set(files)
    moved: dict[str, str] = {}
    for name in present:
        target = names.get(name, name)
        if target != name:
            (folder / target).parent.mkdir(parents=True, exist_ok=True)
            shutil.move(folder / name, folder / target)
        moved[name] = target
    for ply, gii in _gifti_names(label).items():
        if ply in present:
            mesh = decode_ply((folder / moved[ply]).read_bytes(), name=ply)
            (folder / gii).write_bytes(encode_gifti_surface(mesh.vertices, mesh.faces))
            moved[gii] = gii
    for name, doc in _sidecars(label, present, metrics, volume_methods, raw_uri).items():
        side = moved[name].removesuffix(".nii.gz") + ".json"
        (folder / side).write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
        moved[side] = side
    return moved
