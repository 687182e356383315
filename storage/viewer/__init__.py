"""The patient's viewer page (``viewer.html``): MR slices with the mask beside the 3-D view.

:func:`viewer_html` returns one HTML page that shows, in the browser and
offline, the MR image in three planes (axial, coronal, sagittal) with the
tumour mask over it and the brain mask on demand, and beside them a 3-D
pane with the tumour surface inside the translucent brain surface. Clicking
or dragging in a plane moves the cross-hair (the other planes follow), the
wheel steps through slices, the right button drags the contrast, dragging
the 3-D pane rotates it; check boxes show or hide each layer. The display is
radiological by default (the patient's right on the screen's left, as the
overlay mosaics and the renders show it), neurological at a click.

It is drawn by NiiVue (``@niivue/niivue``, BSD-2-Clause; WebGL2), the
viewer of the neuroimaging field, vendored unmodified in
``storage/assets/`` (version, SHA-256 and licences there). Why NiiVue and
not a self-written viewer or the earlier plotly page: it reads NIfTI with
its affine (the page holds the same kind of file the folder publishes, in
RAS millimetres, so slices, masks and meshes line up by construction, with
anatomical labels), it draws the three planes, the overlays and the meshes
in one canvas, and a clinician gets the interactions of the tools they use.
Its one file (2.3 MB) is written **once per output folder**,
``<out>/_assets/niivue-<version>.umd.js``, by :func:`write_viewer_assets`,
and every page loads it as ``../_assets/...``: a page moved out of its
output folder says which file it is missing instead of drawing nothing.

A page from ``file://`` cannot fetch its neighbours, so the data travel in
the page: the image and masks as gzip NIfTI (base64) cropped to the box of
the brain and tumour plus :data:`CROP_MARGIN_MM`, the image scaled to 8 bits
between its 0.5th and 99.5th percentiles inside that box (a display copy;
the right button still adjusts the contrast), the finest axis subsampled
when the crop exceeds ``max_voxels``; the meshes as base64 float32 vertices
and uint16/uint32 faces. 1.0 MB for the demo phantom (30 thick slices,
``benchmarks/bench_viewer.py``); the image of a 1-mm 3-D FLAIR (BraTS,
155 x 240 x 240) takes 1.04 MB of it. The same inputs give the same bytes.

When it has drawn, the page records what it loaded in its status element
(``id="t3d-status"``, ``data-state="ready"``, the tumour and brain voxel
counts it read, the meshes): what the browser tests check.

The package: the shared NiiVue assets and :func:`viewer_html` here,
:mod:`~tumor3d.storage.viewer.volume` (the volumes the page embeds) and
:mod:`~tumor3d.storage.viewer.template` (the page's template and the JSON it embeds).
The public names are importable from here.
"""

from __future__ import annotations

import contextlib
import hashlib
import html
import json
from collections.abc import Sequence
from importlib import resources
from pathlib import Path

import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.storage.atomic import atomic_write_bytes
from tumor3d.storage.nifti import encode_nifti
from tumor3d.storage.refs import StoreError
from tumor3d.storage.viewer.template import _BRAIN_ROW, _PAGE, _b64, _centre_mm, _mesh_json, _rgb255
from tumor3d.storage.viewer.volume import CROP_MARGIN_MM, MAX_VIEWER_VOXELS, _mask, viewer_volume

__all__ = [
    "ASSETS_DIR",
    "CROP_MARGIN_MM",
    "MAX_VIEWER_VOXELS",
    "NIIVUE_FILE",
    "NIIVUE_LICENSES_FILE",
    "NIIVUE_SHA256",
    "NIIVUE_VERSION",
    "viewer_assets",
    "viewer_html",
    "viewer_volume",
    "write_viewer_assets",
]


#: The vendored NiiVue release (``storage/assets/README.md``).
NIIVUE_VERSION = "0.69.0"
#: SHA-256 of ``storage/assets/niivue.umd.js`` (checked before it is published).
NIIVUE_SHA256 = "47b896b77ec4a5be3ef1949c33ad393b6f45629921f326c279000bcf51bdb4af"
#: The folder, beside the patient folders, that holds the shared JavaScript.
ASSETS_DIR = "_assets"
#: Published names of the script and of its licences.
NIIVUE_FILE = f"niivue-{NIIVUE_VERSION}.umd.js"
NIIVUE_LICENSES_FILE = f"niivue-{NIIVUE_VERSION}-LICENSES.txt"


_PACKAGED = {NIIVUE_FILE: "niivue.umd.js", NIIVUE_LICENSES_FILE: "niivue-LICENSES.txt"}


def viewer_assets() -> dict[str, bytes]:
    """The files of ``<out>/_assets/``: published name -> content.

    Raises
    ------
    StoreError
        When the packaged script is missing or not the vendored release
        (a broken installation: one line saying so, no traceback).
    """
    files = {}
    root = resources.files("tumor3d.storage").joinpath("assets")
    for name, packaged in _PACKAGED.items():
        try:
            files[name] = root.joinpath(packaged).read_bytes()
        except OSError as exc:
            raise StoreError(
                f"the viewer's packaged assets/{packaged} of tumor3d.storage cannot be read "
                f"({exc.strerror or exc}): reinstall tumor3d"
            ) from None
    if hashlib.sha256(files[NIIVUE_FILE]).hexdigest() != NIIVUE_SHA256:
        raise StoreError(
            f"assets/niivue.umd.js of tumor3d.storage is not NiiVue {NIIVUE_VERSION} "
            "(SHA-256 differs from the README.md beside it): reinstall tumor3d"
        )
    return files


def write_viewer_assets(out_dir: str | Path) -> list[str]:
    """Write the viewer's JavaScript and licences to ``out_dir/_assets/``; the names written.

    A file already there with the same bytes is left alone (not rewritten,
    its time unchanged); a missing or different one is written to a
    temporary name in the same folder, fsynced and renamed over the final
    name (:func:`~tumor3d.storage.atomic.atomic_write_bytes`), so a reader never
    sees it half-written.
    """
    assets = viewer_assets()
    folder = Path(out_dir) / ASSETS_DIR
    made = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    try:
        for name, data in assets.items():
            final = folder / name
            try:
                if (
                    final.is_file()
                    and final.stat().st_size == len(data)
                    and final.read_bytes() == data
                ):
                    continue
            except OSError:
                pass
            atomic_write_bytes(final, data)
            written.append(name)
    except OSError:
        if made:  # a folder this call made and could not fill (a full disk) is not left
            with contextlib.suppress(OSError):  # another writer's files there: it stays
                for name in written:
                    (folder / name).unlink(missing_ok=True)
                folder.rmdir()
        raise
    return written


def viewer_html(
    image_zyx: np.ndarray,
    affine: np.ndarray,
    tumour_zyx: np.ndarray,
    *,
    brain_zyx: np.ndarray | None = None,
    tumour_mesh: Mesh | None = None,
    brain_mesh: Mesh | None = None,
    title: str = "tumor3d viewer",
    tumor_color_rgb: Sequence[float] = (0.85, 0.35, 0.3),
    brain_color_rgb: Sequence[float] = (0.78, 0.78, 0.82),
    brain_opacity: float = 0.25,
    radiological: bool = True,
    assets_href: str = f"../{ASSETS_DIR}",
    margin_mm: float = CROP_MARGIN_MM,
    max_voxels: int = MAX_VIEWER_VOXELS,
) -> str:
    """The viewer page as an HTML string (see the module docstring).

    Parameters
    ----------
    image_zyx : ndarray, shape (z, y, x)
        The MR image.
    affine : (4, 4) array_like
        Maps ``(x, y, z, 1)`` voxel indices to RAS mm.
    tumour_zyx : ndarray, shape (z, y, x)
        The tumour mask on the image's grid, drawn red over the slices (may be empty).
    brain_zyx : ndarray, shape (z, y, x), optional
        The brain mask, drawn blue on demand.
    tumour_mesh, brain_mesh : Mesh, optional
        Surfaces in RAS mm for the 3-D pane (empty meshes are left out).
    title : str
        Page title (HTML-escaped).
    tumor_color_rgb, brain_color_rgb : sequence of 3 float
        Surface colours, components in [0, 1].
    brain_opacity : float
        Opacity of the brain surface, in (0, 1].
    radiological : bool
        Radiological display (the patient's right on the screen's left, as
        the overlay mosaics and the renders show it) or neurological; a check
        box of the page switches it.
    assets_href : str
        Relative URL of the folder that holds :data:`NIIVUE_FILE`.
    margin_mm, max_voxels
        See :func:`viewer_volume`.

    Returns
    -------
    str
        A complete HTML document.

    Raises
    ------
    InputError
        On arrays of different shapes, a bad affine, a non-mesh or a bad parameter.
    """
    if not isinstance(title, str):
        raise InputError(f"title must be a string, got {type(title).__name__}")
    if (
        isinstance(brain_opacity, bool)
        or not isinstance(brain_opacity, (int, float))
        or not (0.0 < brain_opacity <= 1.0)
    ):
        raise InputError(f"brain_opacity must lie in (0, 1], got {brain_opacity!r}")
    if not isinstance(radiological, bool):
        raise InputError(f"radiological must be True or False, got {radiological!r}")
    if not isinstance(assets_href, str) or "://" in assets_href or assets_href.startswith("/"):
        raise InputError(f"assets_href must be a relative URL, got {assets_href!r}")
    tumour_rgb = _rgb255(tumor_color_rgb, "tumor_color_rgb")
    brain_rgb = _rgb255(brain_color_rgb, "brain_color_rgb")
    for mesh, name in ((tumour_mesh, "tumour_mesh"), (brain_mesh, "brain_mesh")):
        if mesh is not None and not isinstance(mesh, Mesh):
            raise InputError(
                f"{name} must be a tumor3d.geometry.mesh.Mesh, got {type(mesh).__name__}"
            )
    shape = np.shape(image_zyx)
    _mask(tumour_zyx, shape, "the tumour mask")
    if brain_zyx is not None:
        _mask(brain_zyx, shape, "the brain mask")
    masks = [tumour_zyx] if brain_zyx is None else [tumour_zyx, brain_zyx]
    u8, small, aff = viewer_volume(
        image_zyx, affine, masks, margin_mm=margin_mm, max_voxels=max_voxels
    )
    # the cross-hair starts at the tumour's centre (else the brain's, else the middle)
    centre = _centre_mm(small[0], aff)
    if centre is None and brain_zyx is not None:
        centre = _centre_mm(small[1], aff)
    data: dict = {
        "image": _b64(encode_nifti(u8.transpose(2, 1, 0), aff, dtype=np.uint8)),
        "tumour_mask": _b64(encode_nifti(small[0].transpose(2, 1, 0), aff, dtype=np.uint8)),
        "centre_mm": centre,
        "radiological": radiological,
        "meshes": [],
    }
    if brain_zyx is not None:
        data["brain_mask"] = _b64(encode_nifti(small[1].transpose(2, 1, 0), aff, dtype=np.uint8))
    if tumour_mesh is not None and not tumour_mesh.is_empty:
        data["meshes"].append(_mesh_json(tumour_mesh, "tumour surface", tumour_rgb, 1.0))
    if brain_mesh is not None and not brain_mesh.is_empty:
        data["meshes"].append(
            _mesh_json(brain_mesh, "brain surface", brain_rgb, float(brain_opacity))
        )
    # "</" cannot end the JSON's script element early: base64 and numbers hold no "<"
    payload = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    src = f"{assets_href.rstrip('/')}/{NIIVUE_FILE}"
    return _PAGE.format(
        title=html.escape(title),
        src=html.escape(src, quote=True),
        src_js=json.dumps(src),
        data=payload,
        brain_row="" if brain_zyx is None else _BRAIN_ROW,
        radiological_checked=" checked" if radiological else "",
    )
