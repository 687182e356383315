"""The page's HTML and JavaScript template and the JSON values it embeds.

Colours, meshes and the centre of the view.
"""

from __future__ import annotations

import base64
from collections.abc import Sequence

import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh


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
