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
``tumor3d/storage/assets/`` (version, SHA-256 and licences there). Why NiiVue and
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
"""

from __future__ import annotations

import base64
import hashlib
import html
import json
import os
import uuid
from collections.abc import Sequence
from importlib import resources
from pathlib import Path

import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.storage.nifti import encode_nifti
from tumor3d.storage.store import StoreError
from tumor3d.validation import check_affine

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

#: The vendored NiiVue release (``tumor3d/storage/assets/README.md``).
NIIVUE_VERSION = "0.69.0"
#: SHA-256 of ``tumor3d/storage/assets/niivue.umd.js`` (checked before it is published).
NIIVUE_SHA256 = "47b896b77ec4a5be3ef1949c33ad393b6f45629921f326c279000bcf51bdb4af"
#: The folder, beside the patient folders, that holds the shared JavaScript.
ASSETS_DIR = "_assets"
#: Published names of the script and of its licences.
NIIVUE_FILE = f"niivue-{NIIVUE_VERSION}.umd.js"
NIIVUE_LICENSES_FILE = f"niivue-{NIIVUE_VERSION}-LICENSES.txt"
#: Margin kept around the brain and tumour when the image is cropped (mm).
CROP_MARGIN_MM = 10.0
#: Largest image the page embeds (voxels); beyond it the finest axis is subsampled.
MAX_VIEWER_VOXELS = 4_000_000

_PACKAGED = {NIIVUE_FILE: "niivue.umd.js", NIIVUE_LICENSES_FILE: "niivue-LICENSES.txt"}


# ---------------------------------------------------------------------------
# the shared assets


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
                f"the viewer's packaged tumor3d/storage/assets/{packaged} cannot be read "
                f"({exc.strerror or exc}): reinstall tumor3d"
            ) from None
    if hashlib.sha256(files[NIIVUE_FILE]).hexdigest() != NIIVUE_SHA256:
        raise StoreError(
            f"tumor3d/storage/assets/niivue.umd.js is not NiiVue {NIIVUE_VERSION} "
            "(SHA-256 differs from tumor3d/storage/assets/README.md): reinstall tumor3d"
        )
    return files


def write_viewer_assets(out_dir: str | Path) -> list[str]:
    """Write the viewer's JavaScript and licences to ``out_dir/_assets/``; the names written.

    A file already there with the same bytes is left alone (not rewritten,
    its time unchanged); a missing or different one is written to a
    temporary name in the same folder, fsynced and renamed over the final
    name, so a reader never sees it half-written.
    """
    assets = viewer_assets()
    folder = Path(out_dir) / ASSETS_DIR
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, data in assets.items():
        final = folder / name
        try:
            if final.is_file() and final.stat().st_size == len(data) and final.read_bytes() == data:
                continue
        except OSError:
            pass
        tmp = folder / f".{name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp"
        try:
            with open(tmp, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, final)
        finally:
            tmp.unlink(missing_ok=True)
        written.append(name)
    return written


# ---------------------------------------------------------------------------
# the volumes the page embeds


def _mask(arr: object, shape: tuple[int, ...], name: str) -> np.ndarray:
    a = np.asarray(arr)
    if a.shape != shape:
        raise InputError(f"{name} has shape {a.shape}, the image {shape}: they must match")
    return a.astype(bool)


def viewer_volume(
    image_zyx: np.ndarray,
    affine: np.ndarray,
    masks: Sequence[np.ndarray],
    *,
    margin_mm: float = CROP_MARGIN_MM,
    max_voxels: int = MAX_VIEWER_VOXELS,
) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """The display copy of an image and its masks: cropped, subsampled, 8-bit.

    Parameters
    ----------
    image_zyx : ndarray, shape (z, y, x)
        The MR image (any real dtype). Not modified.
    affine : (4, 4) array_like
        Maps ``(x, y, z, 1)`` voxel indices to RAS mm.
    masks : sequence of ndarray, shape (z, y, x)
        Masks on the image's grid; the crop box is that of their union
        (the whole image when they are all empty) plus ``margin_mm``.
    margin_mm : float
        Margin around the box, mm (>= 0).
    max_voxels : int
        Largest number of voxels kept: beyond it the axis with the finest
        spacing (after subsampling) is subsampled by one more step, until it fits.

    Returns
    -------
    image : uint8 ndarray, shape (z', y', x')
        Intensities scaled linearly between the 0.5th and 99.5th
        percentiles of the cropped image (clipped; non-finite values are 0).
    masks : list of bool ndarray, shape (z', y', x')
    affine : (4, 4) float64 ndarray
        Maps the new ``(x, y, z, 1)`` indices to the same RAS mm.

    Examples
    --------
    >>> img = np.arange(4 * 50 * 60, dtype=float).reshape(4, 50, 60)
    >>> m = np.zeros(img.shape, bool); m[1:3, 20:30, 10:20] = True
    >>> small, (m2,), aff = viewer_volume(img, np.eye(4), [m], margin_mm=2)
    >>> small.shape, int(m2.sum()) == int(m.sum()), aff[:3, 3].tolist()
    ((4, 14, 14), True, [8.0, 18.0, 0.0])
    """
    img = np.asarray(image_zyx)
    if img.ndim != 3 or min(img.shape) < 1:
        raise InputError(f"the image must be a non-empty 3-D array, got shape {img.shape}")
    if not (np.issubdtype(img.dtype, np.number) or img.dtype == bool):
        raise InputError(f"the image must hold numbers, got dtype {img.dtype}")
    aff = check_affine(affine)
    if (
        isinstance(margin_mm, bool)
        or not isinstance(margin_mm, (int, float))
        or not np.isfinite(margin_mm)
        or margin_mm < 0
    ):
        raise InputError(f"margin_mm must be a finite number >= 0, got {margin_mm!r}")
    if isinstance(max_voxels, bool) or not isinstance(max_voxels, int) or max_voxels < 1:
        raise InputError(f"max_voxels must be a positive integer, got {max_voxels!r}")
    ms = [_mask(m, img.shape, f"mask {i} of {len(masks)}") for i, m in enumerate(masks)]
    # spacing of the (z, y, x) axes: lengths of the affine's columns (z, y, x) = (2, 1, 0)
    spacing = np.linalg.norm(aff[:3, [2, 1, 0]], axis=0)
    union = np.zeros(img.shape, bool)
    for m in ms:
        union |= m
    lo = np.zeros(3, np.int64)
    hi = np.array(img.shape, np.int64)
    if union.any():
        pad = np.ceil(margin_mm / spacing).astype(np.int64)
        for ax in range(3):
            other = tuple(a for a in range(3) if a != ax)
            idx = np.flatnonzero(union.any(axis=other))
            lo[ax] = max(0, idx[0] - pad[ax])
            hi[ax] = min(img.shape[ax], idx[-1] + 1 + pad[ax])
    step = np.ones(3, np.int64)
    while int(np.prod(-(-(hi - lo) // step))) > max_voxels:
        finest = int(np.argmin(np.where(-(-(hi - lo) // step) > 1, spacing * step, np.inf)))
        step[finest] += 1
    box = tuple(slice(int(a), int(b), int(s)) for a, b, s in zip(lo, hi, step, strict=True))
    crop = np.asarray(img[box], dtype=np.float64)
    finite = np.isfinite(crop)
    if finite.any():
        p_lo, p_hi = np.percentile(crop[finite], [0.5, 99.5])
    else:
        p_lo = p_hi = 0.0
    scale = 255.0 / (p_hi - p_lo) if p_hi > p_lo else 0.0
    scaled = np.where(finite, (np.where(finite, crop, p_lo) - p_lo) * scale, 0.0)
    u8 = np.clip(np.rint(scaled), 0, 255).astype(np.uint8)
    # new index (x, y, z) -> old index lo + step * new (xyz order: reverse of zyx)
    sub = np.eye(4)
    sub[:3, :3] = np.diag(step[::-1].astype(np.float64))
    sub[:3, 3] = lo[::-1]
    return u8, [np.ascontiguousarray(m[box]) for m in ms], aff @ sub


# ---------------------------------------------------------------------------
# the page


def _rgb255(rgb: Sequence[float], name: str) -> list[int]:
    arr = np.asarray(rgb, dtype=np.float64)
    if arr.shape != (3,) or not np.all((arr >= 0) & (arr <= 1)):
        raise InputError(f"{name} must be 3 numbers in [0, 1], got {rgb!r}")
    return [int(round(255 * c)) for c in arr]


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def _mesh_json(mesh: Mesh, name: str, rgb: list[int], opacity: float) -> dict:
    v = np.round(np.asarray(mesh.vertices, dtype=np.float64), 2).astype("<f4")
    wide = mesh.n_vertices > 65536
    f = np.asarray(mesh.faces).astype("<u4" if wide else "<u2")
    return {
        "name": name,
        "vertices": _b64(v.tobytes()),
        "faces": _b64(f.tobytes()),
        "index_bytes": 4 if wide else 2,
        "rgba": [*rgb, 255],
        "opacity": opacity,
    }


def _centre_mm(mask_zyx: np.ndarray, affine: np.ndarray) -> list[float] | None:
    """RAS mm of the mask voxel nearest the mask's centroid (inside the mask), or None."""
    if not mask_zyx.any():
        return None
    idx = np.argwhere(mask_zyx).astype(np.float64)
    mm = idx[:, ::-1] @ affine[:3, :3].T + affine[:3, 3]
    nearest = mm[np.argmin(((mm - mm.mean(axis=0)) ** 2).sum(axis=1))]
    return [round(float(c), 3) for c in nearest]


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


_BRAIN_ROW = (
    '<label><input type="checkbox" id="t3d-brainmask"> brain mask '
    '<span class="key" style="background:#3c78ff"></span></label>'
)

_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<style>
html, body {{ margin: 0; height: 100%; background: #000; color: #ddd;
  font: 14px system-ui, sans-serif; }}
body {{ display: flex; flex-direction: column; }}
#t3d-bar {{ display: flex; flex-wrap: wrap; gap: .3em 1.2em; align-items: center;
  padding: .4em .8em; background: #1d1d1d; }}
#t3d-bar h1 {{ font-size: 15px; margin: 0 .6em 0 0; }}
.key {{ display: inline-block; width: .8em; height: .8em; vertical-align: middle; }}
#t3d-pane {{ position: relative; flex: 1; min-height: 300px; }}
#t3d-gl {{ position: absolute; width: 100%; height: 100%; }}
#t3d-status {{ margin: 0; padding: .3em .8em; background: #1d1d1d; color: #aaa; font-size: 12px; }}
#t3d-status[data-state="error"] {{ background: #fff3cd; color: #5c4400; font-size: 15px;
  padding: 1em; }}
</style>
</head>
<body>
<div id="t3d-bar">
<h1>{title}</h1>
<label><input type="checkbox" id="t3d-tumourmask" checked> tumour mask
<span class="key" style="background:#ff3c3c"></span></label>
<label>opacity <input type="range" id="t3d-opacity" min="0.1" max="1" step="0.05"
value="0.5"></label>
{brain_row}
<span id="t3d-meshes"></span>
<label title="radiological: the patient's right on the screen's left"><input type="checkbox"
id="t3d-radiological"{radiological_checked}> radiological</label>
<button type="button" id="t3d-centre">centre on the tumour</button>
<span id="t3d-where"></span>
</div>
<div id="t3d-pane"><canvas id="t3d-gl"></canvas></div>
<p id="t3d-status" data-state="loading">Loading the viewer&hellip;
<noscript>The viewer needs JavaScript.</noscript></p>
<script type="application/json" id="t3d-data">{data}</script>
<script src="{src}"></script>
<script>
(function () {{
  "use strict";
  var SRC = {src_js};
  var status = document.getElementById("t3d-status");
  function fail(msg) {{
    status.setAttribute("data-state", "error");
    status.textContent = msg;
    document.getElementById("t3d-pane").style.display = "none";
  }}
  if (typeof niivue === "undefined") {{
    fail("The viewer's JavaScript, " + SRC + " (relative to this page), is missing. " +
      "This page loads it from the _assets folder beside the patient folders that " +
      "tumor3d writes: open it inside its output folder, or copy that _assets folder " +
      "next to the folder that holds this page.");
    return;
  }}
  if (!document.createElement("canvas").getContext("webgl2")) {{
    fail("This browser cannot draw the viewer: it needs WebGL2 " +
      "(Chrome/Edge 56+, Firefox 51+, Safari 15+ with hardware acceleration on).");
    return;
  }}
  var data = JSON.parse(document.getElementById("t3d-data").textContent);
  function bytes(b64) {{
    var s = atob(b64), out = new Uint8Array(s.length);
    for (var i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
    return out;
  }}
  function count(img) {{
    var n = 0, a = img.img;
    for (var i = 0; i < a.length; i++) if (a[i] > 0) n++;
    return n;
  }}
  var nv = new niivue.Niivue({{
    backColor: [0, 0, 0, 1],
    crosshairColor: [0.2, 0.8, 1.0, 0.5],
    crosshairWidth: 1,
    crosshairGap: 12,
    show3Dcrosshair: true,
    isColorbar: false,
    isOrientCube: false,
    dragAndDropEnabled: false,
    meshThicknessOn2D: 0,
    multiplanarShowRender: niivue.SHOW_RENDER.ALWAYS,
    multiplanarLayout: niivue.MULTIPLANAR_TYPE.GRID,
    isRadiologicalConvention: data.radiological,
    logLevel: "error",
    loadingText: "loading"
  }});
  var maskIdx = 1, brainIdx = -1;
  async function run() {{
    await nv.attachTo("t3d-gl");
    var vols = [
      await niivue.NVImage.loadFromBase64({{ base64: data.image, name: "mr.nii.gz",
        cal_min: 0, cal_max: 255, trustCalMinMax: true }}),
      await niivue.NVImage.loadFromBase64({{ base64: data.tumour_mask, name: "tumour.nii.gz",
        colormap: "red", opacity: 0.5, cal_min: 0, cal_max: 1, trustCalMinMax: true }})
    ];
    if (data.brain_mask) {{
      vols.push(await niivue.NVImage.loadFromBase64({{ base64: data.brain_mask,
        name: "brain.nii.gz", colormap: "blue", opacity: 0, cal_min: 0, cal_max: 1,
        trustCalMinMax: true }}));
      brainIdx = 2;
    }}
    vols.forEach(function (v) {{ nv.addVolume(v); }});
    var meshBox = document.getElementById("t3d-meshes");
    data.meshes.forEach(function (m) {{
      var pts = new Float32Array(bytes(m.vertices).buffer);
      var raw = bytes(m.faces).buffer;
      var tris = new Uint32Array(m.index_bytes === 2 ? new Uint16Array(raw) : new Uint32Array(raw));
      var mesh = new niivue.NVMesh(pts, tris, m.name, new Uint8Array(m.rgba), m.opacity, true,
        nv.gl);
      nv.addMesh(mesh);
      var label = document.createElement("label");
      var box = document.createElement("input");
      box.type = "checkbox"; box.checked = true;
      box.addEventListener("change", function () {{
        nv.setMeshProperty(mesh.id, "visible", box.checked);
      }});
      label.appendChild(box);
      label.appendChild(document.createTextNode(" " + m.name + " (3-D)"));
      meshBox.appendChild(label);
    }});
    nv.setSliceType(niivue.SLICE_TYPE.MULTIPLANAR);
    // the 3-D pane: the three planes at the cross-hair (not a volume rendering) with the
    // surfaces, so that the surfaces are not hidden inside the rendered head
    await nv.setVolumeRenderIllumination(-1);
    nv.setRenderAzimuthElevation(120, 15);
    function centre() {{
      if (data.centre_mm) {{
        nv.scene.crosshairPos = nv.mm2frac(data.centre_mm);
        nv.drawScene();
        nv.createOnLocationChange();
      }}
    }}
    var opacity = document.getElementById("t3d-opacity");
    var shown = document.getElementById("t3d-tumourmask");
    function maskOpacity() {{
      nv.setOpacity(maskIdx, shown.checked ? parseFloat(opacity.value) : 0);
    }}
    shown.addEventListener("change", maskOpacity);
    opacity.addEventListener("input", maskOpacity);
    var radio = document.getElementById("t3d-radiological");
    radio.addEventListener("change", function () {{
      nv.setRadiologicalConvention(radio.checked);
      status.setAttribute("data-radiological", String(radio.checked));
    }});
    status.setAttribute("data-radiological", String(data.radiological));
    var brainBox = document.getElementById("t3d-brainmask");
    if (brainBox) brainBox.addEventListener("change", function () {{
      nv.setOpacity(brainIdx, brainBox.checked ? 0.35 : 0);
    }});
    var where = document.getElementById("t3d-where");
    // the cursor: RAS millimetres, the display intensity and the masks at that voxel
    nv.onLocationChange = function (loc) {{
      var mm = Array.prototype.slice.call(loc.mm || [], 0, 3), v = loc.values || [];
      var text = "cursor RAS " + mm.map(function (c) {{ return c.toFixed(1); }}).join(", ") +
        " mm";
      if (v[0]) text += "; MR " + Math.round(v[0].value);
      if (v[1]) text += "; tumour mask: " + (v[1].value > 0 ? "yes" : "no");
      if (brainIdx >= 0 && v[2]) text += "; brain mask: " + (v[2].value > 0 ? "yes" : "no");
      where.textContent = text;
    }};
    centre();
    document.getElementById("t3d-centre").addEventListener("click", centre);
    status.textContent = "Red: the tumour mask on the MR slices" +
      (brainIdx >= 0 ? "; blue: the brain mask" : "") +
      ". Click or drag in a plane to move the cross-hair, wheel: next slice, " +
      "right-drag: contrast; drag the 3-D pane to rotate it.";
    status.setAttribute("data-tumour-voxels", String(count(vols[1])));
    if (brainIdx >= 0) status.setAttribute("data-brain-voxels", String(count(vols[2])));
    status.setAttribute("data-meshes", data.meshes.map(function (m) {{ return m.name; }})
      .join(","));
    // where each plane is drawn (CSS pixels of the page), once the layout has settled
    function tiles() {{
      nv.drawScene();
      var r = nv.canvas.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
      var planes = ["axial", "coronal", "sagittal", "multiplanar", "3-D"];
      status.setAttribute("data-tiles", JSON.stringify(nv.screenSlices.map(function (t) {{
        var b = t.leftTopWidthHeight;
        return {{ plane: planes[t.axCorSag] || String(t.axCorSag),
          box: [r.left + b[0] / dpr, r.top + b[1] / dpr, b[2] / dpr, b[3] / dpr] }};
      }})));
      status.setAttribute("data-state", "ready");
    }}
    window.addEventListener("resize", function () {{ setTimeout(tiles, 100); }});
    setTimeout(tiles, 100);
  }}
  run().catch(function (e) {{ fail("The viewer could not draw this patient: " + e); }});
}})();
</script>
</body>
</html>
"""
