"""Offscreen rendering of a tumour surface (spec section 7).

:func:`render_views` returns one RGB image per camera azimuth: the mesh seen
from a camera orbiting its centroid around the RAS superior axis, lit by a
headlight, with smooth (per-vertex normal, per-fragment interpolated)
shading. :func:`vertex_normals` computes the normals of spec section 7,
``n_v = normalise(sum of the unit normals of the faces at v)``, in numpy.

Camera convention
-----------------
The camera looks at the area-weighted surface centroid ``c`` from
``c + d * (sin(az) cos(el), cos(az) cos(el), sin(el))`` in RAS, with the
superior axis ``+S`` up: azimuth 0 is the anterior view (the patient's right
appears on the image's left, as in radiological display), azimuth 90 the
view from the patient's right, positive elevation looks down from above.
``d`` is chosen so that the bounding sphere of the mesh (about ``c``) fits in
the smaller of the vertical and horizontal fields of view, with 5 % margin.

Lighting
--------
One white directional light travelling along the viewing direction
(a headlight) plus a weak image-based ambient term, Filament's ``defaultLit``
(physically based, metallic 0) material. The intensities are calibrated so
that a surface facing the camera receives about ``k_a + k_d = 0.15 + 0.7``
of its base colour plus a specular highlight ([A25]); post-processing (tone
mapping, colour grading, FXAA) is disabled so that colours are not
remapped. With post-processing disabled Filament writes linear values to
the 8-bit target while ``set_background`` decodes its argument as sRGB, so
the background is passed sRGB-*encoded* and comes out exactly (within one
level) as requested; the mesh colour is used as the linear albedo, which
gives the classic display-space Phong look.

Design: one subprocess per call
-------------------------------
Measurements of Open3D's Filament renderer (open3d-cpu 0.20, Mesa 22.3
llvmpipe through Filament's Vulkan backend, headless: no DISPLAY needed) on
this 2-core machine, shared with other jobs:

* a fresh process: ``import open3d`` 0.6-0.9 s, ``OffscreenRenderer``
  creation ~0.1 s, first frame ~0.3 s (about 1.5 s more while the Mesa
  shader cache in ``~/.cache/mesa_shader_cache`` is cold), later frames
  0.07-0.1 s at 320x240 and ~0.1-0.4 s at 640x480;
* a second renderer created after deleting the first works, with the same
  timings (first frame ~0.3 s);
* meshes given as the *legacy* ``o3d.geometry.TriangleMesh`` made some
  frames take 5-100 s instead of 0.1 s, erratically: it depended on the mesh
  (a marching-cubes ball of radius 9 voxels: 25 s then 65 s; radius 10:
  0.3 s) and on whether Open3D geometry had been built before the renderer
  was created -- the "first render took 15 s" seen earlier. The
  tensor-based ``o3d.t.geometry.TriangleMesh`` never showed this: all the
  same cases render in 0.1-0.3 s per frame, so it is used here;
* rendering from any thread other than the one that created the (process-
  wide) Filament engine aborts the whole process (``PreconditionPanic``:
  "This thread has not been adopted"), and so does creating a second
  renderer in a new thread; two renderers alive at once in one thread work
  but abort the process at exit ("destroying MaterialInstance ... still in
  use"). Prefect may run tasks in worker threads, so an in-process
  renderer would be a process-killing hazard.

So every :func:`render_views` call runs the renderer in a fresh child
process (``python -m tumor3d.render``). The mesh and camera set-up go to the
child's stdin and the images come back on a private copy of its stdout, as
``.npy`` bytes (no pickle, no temporary files); Filament's C++ messages
("FEngine ...", "Selected physical device ...", printed whatever Open3D's
verbosity) are diverted to the child's stderr, which is shown only if the
child fails. The child leaves with ``os._exit`` once the images are
written, skipping Filament's teardown. Cost: a 4-view 640x480 render of a
10k-face mesh takes 2-3 s wall time in total, most of it Python start-up and
the Open3D import. The calling process never imports Open3D, may call from
any thread, and survives a crash of the renderer, reported as a
``RuntimeError`` carrying the child's error output.
"""

from __future__ import annotations

import io
import math
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from tumor3d.errors import InputError
from tumor3d.mesh import Mesh

__all__ = ["render_views", "vertex_normals"]

#: Headlight and ambient settings ([A25]); see the module docstring.
_K_AMBIENT = 0.15
_K_DIFFUSE = 0.7
# Measured: a directional light of 100 000 lux gives a radiance of 0.47 x the
# albedo on a surface facing it (Open3D's default camera exposure), and the
# default image-based light at 30 000 gives 0.47 on average.
_SUN_LUX_PER_UNIT = 100_000.0 / 0.47
_IBL_PER_UNIT = 30_000.0 / 0.47
_ROUGHNESS = 0.4
_REFLECTANCE = 0.5
_MARGIN = 1.05
_DEFAULT_TIMEOUT_S = 600.0


# ---------------------------------------------------------------------------
# geometry (pure numpy, in the calling process)
# ---------------------------------------------------------------------------


def vertex_normals(mesh: Mesh) -> np.ndarray:
    r"""Per-vertex normals: unweighted mean of the adjacent face normals.

    .. math:: n_v = \frac{\sum_{t \ni v} \hat n_t}{\lVert \sum_{t \ni v} \hat n_t \rVert}

    as in spec section 7 (every face counts once, whatever its area).
    Zero-area faces contribute nothing; a vertex with no usable face (or
    whose normals cancel) gets ``(0, 0, 1)``.

    Parameters
    ----------
    mesh : Mesh
        Faces counter-clockwise seen from outside.

    Returns
    -------
    (n_vertices, 3) float64 ndarray
        Unit outward normals.
    """
    if not isinstance(mesh, Mesh):
        raise InputError(f"mesh must be a tumor3d.mesh.Mesh, got {type(mesh).__name__}")
    v, f = mesh.vertices, mesh.faces
    out = np.zeros((len(v), 3))
    if len(f):
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        norm = np.linalg.norm(fn, axis=1, keepdims=True)
        fn = np.divide(fn, norm, out=np.zeros_like(fn), where=norm > 0)
        for k in range(3):
            out[:, k] = np.bincount(f.reshape(-1), weights=np.repeat(fn[:, k], 3), minlength=len(v))
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    tiny = norm[:, 0] <= 1e-12
    out = np.divide(out, norm, out=np.zeros_like(out), where=~tiny[:, None])
    out[tiny] = (0.0, 0.0, 1.0)
    return out


def _surface_centroid(mesh: Mesh) -> np.ndarray:
    v, f = mesh.vertices, mesh.faces
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = area.sum()
    if total <= 0:
        return v[np.unique(f)].mean(axis=0)
    return (tri.mean(axis=1) * area[:, None]).sum(axis=0) / total


def _srgb_encode(c: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)


def _check_color(value: Sequence[float], name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be 3 numbers in [0, 1], got {value!r}") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)) or arr.min() < 0 or arr.max() > 1:
        raise InputError(f"{name} must be 3 numbers in [0, 1], got {value!r}")
    return arr


def _check_number(value: float, name: str, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and lo < v < hi):
        raise InputError(f"{name} must lie strictly between {lo} and {hi}, got {value}")
    return v


def render_views(
    mesh: Mesh,
    *,
    width: int,
    height: int,
    azimuths_deg: Sequence[float],
    elevation_deg: float,
    field_of_view_deg: float,
    color_rgb: Sequence[float],
    background_rgb: Sequence[float],
    timeout_s: float = _DEFAULT_TIMEOUT_S,
) -> list[np.ndarray]:
    """Render a mesh from several azimuths around the superior axis.

    Parameters
    ----------
    mesh : Mesh
        Non-empty surface in RAS mm, faces counter-clockwise seen from
        outside.
    width, height : int
        Image size in pixels, 16-8192 each.
    azimuths_deg : sequence of float
        One image per azimuth (degrees; 0 = anterior view, 90 = from the
        patient's right; see the module docstring).
    elevation_deg : float
        Camera elevation above the axial plane, in (-90, 90) degrees.
    field_of_view_deg : float
        Vertical field of view in (0, 180) degrees.
    color_rgb : sequence of 3 float
        Surface colour, components in [0, 1].
    background_rgb : sequence of 3 float
        Background colour, components in [0, 1]; background pixels equal
        ``round(255 * background_rgb)`` within one level.
    timeout_s : float, optional
        Give up (and kill the rendering process) after this many seconds.

    Returns
    -------
    list of ndarray
        One ``uint8`` image of shape ``(height, width, 3)`` (RGB) per azimuth,
        in the order given.

    Raises
    ------
    InputError
        On an empty mesh or an invalid parameter.
    RuntimeError
        If the offscreen renderer fails (Open3D missing, no usable graphics
        driver, crash or timeout); the message carries the renderer's error
        output.
    """
    if not isinstance(mesh, Mesh):
        raise InputError(f"mesh must be a tumor3d.mesh.Mesh, got {type(mesh).__name__}")
    if mesh.is_empty:
        raise InputError("cannot render an empty mesh (it has no faces)")
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise InputError(f"{name} must be an integer number of pixels, got {value!r}")
        if not 16 <= value <= 8192:
            raise InputError(f"{name} must lie in [16, 8192] pixels, got {value}")
    try:
        az = np.asarray(list(azimuths_deg), dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(
            f"azimuths_deg must be a sequence of numbers, got {azimuths_deg!r}"
        ) from None
    if az.ndim != 1 or az.size == 0 or not np.all(np.isfinite(az)):
        raise InputError(
            f"azimuths_deg must be a non-empty sequence of finite numbers, got {azimuths_deg!r}"
        )
    elev = _check_number(elevation_deg, "elevation_deg", -90.0, 90.0)
    fov = _check_number(field_of_view_deg, "field_of_view_deg", 0.0, 180.0)
    color = _check_color(color_rgb, "color_rgb")
    background = _check_color(background_rgb, "background_rgb")
    timeout = _check_number(timeout_s, "timeout_s", 0.0, math.inf)

    request = _build_request(mesh, int(width), int(height), az, elev, fov, color, background)
    images = _run_worker(request, timeout)
    expected = (len(az), int(height), int(width), 3)
    if images.shape != expected or images.dtype != np.uint8:
        raise RuntimeError(
            f"offscreen renderer returned images of shape {images.shape} and dtype "
            f"{images.dtype}, expected {expected} uint8"
        )
    return [np.array(img) for img in images]


def _build_request(
    mesh: Mesh,
    width: int,
    height: int,
    azimuths_deg: np.ndarray,
    elevation_deg: float,
    fov_deg: float,
    color: np.ndarray,
    background: np.ndarray,
) -> dict[str, np.ndarray]:
    """Camera and light set-up for each view, mesh centred on its centroid."""
    centre = _surface_centroid(mesh)
    vertices = mesh.vertices - centre  # centred: better float32 precision in the renderer
    radius = float(np.linalg.norm(vertices[np.unique(mesh.faces)], axis=1).max())
    radius = max(radius, 1e-6)
    half_v = math.radians(fov_deg) / 2.0
    half_h = math.atan(math.tan(half_v) * width / height)
    distance = radius / math.sin(min(half_v, half_h)) * _MARGIN
    a = np.radians(azimuths_deg)
    e = math.radians(elevation_deg)
    to_eye = np.stack(
        [np.sin(a) * math.cos(e), np.cos(a) * math.cos(e), np.full_like(a, math.sin(e))], axis=1
    )
    return {
        "vertices": vertices.astype(np.float64),
        "faces": mesh.faces.astype(np.int32),
        "normals": vertex_normals(mesh),
        "eyes": distance * to_eye,
        "light_dirs": -to_eye,  # a directional light travels from the eye to the object
        "up": np.array([0.0, 0.0, 1.0]),
        "size": np.array([width, height], dtype=np.int64),
        # fov, near, far
        "camera": np.array(
            [fov_deg, max(distance - 1.1 * radius, 1e-3 * distance), distance + 1.1 * radius]
        ),
        "base_color": color,
        "background_srgb": _srgb_encode(background),
        # sun illuminance, ambient (image-based light) intensity, roughness, reflectance
        "light": np.array(
            [
                _K_DIFFUSE * _SUN_LUX_PER_UNIT,
                _K_AMBIENT * _IBL_PER_UNIT,
                _ROUGHNESS,
                _REFLECTANCE,
            ]
        ),
    }


def _run_worker(request: dict[str, np.ndarray], timeout_s: float) -> np.ndarray:
    """Render in a child process; return the stacked ``(k, h, w, 3)`` images."""
    buf = io.BytesIO()
    np.savez(buf, **request)
    env = dict(os.environ)
    package_root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH", "")) if p)
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "tumor3d.render"],
            input=buf.getvalue(),
            capture_output=True,
            timeout=timeout_s,
            env=env,
            check=False,
        )
    except subprocess.TimeoutExpired:
        raise RuntimeError(
            f"offscreen rendering did not finish within {timeout_s:g} s and was stopped"
        ) from None
    except OSError as exc:
        raise RuntimeError(f"offscreen rendering could not start {sys.executable}: {exc}") from None
    if proc.returncode != 0:
        raise RuntimeError(
            f"offscreen rendering failed (exit status {proc.returncode}): "
            f"{_error_tail(proc.stderr)}"
        )
    try:
        return np.load(io.BytesIO(proc.stdout), allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise RuntimeError(
            f"offscreen renderer sent no readable image ({exc}); its output: "
            f"{_error_tail(proc.stderr)}"
        ) from None


_NOISE = (
    "CircularBuffer",
    "FEngine",
    "Vulkan device driver",
    "Selected physical device",
    "Backend feature level",
    "FEngine feature level",
)


def _error_tail(stderr: bytes, n_lines: int = 20) -> str:
    lines = [
        ln
        for ln in stderr.decode("utf-8", errors="replace").splitlines()
        if ln.strip() and not any(tok in ln for tok in _NOISE)
    ]
    return "\n".join(lines[-n_lines:]) or "(no error output)"


# ---------------------------------------------------------------------------
# the child process
# ---------------------------------------------------------------------------


def _worker_main() -> int:
    """Entry point of ``python -m tumor3d.render``: stdin request -> stdout images."""
    out_fd = os.dup(1)  # private copy of the real stdout, for the images only
    os.dup2(2, 1)  # Filament prints on stdout: divert everything else to stderr
    sys.stdout = sys.stderr
    payload = sys.stdin.buffer.read()
    with np.load(io.BytesIO(payload), allow_pickle=False) as data:
        req = {k: data[k] for k in data.files}

    import open3d as o3d  # only ever imported in the child

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    rendering = o3d.visualization.rendering
    width, height = (int(x) for x in req["size"])
    # Renderer first, geometry after: with legacy meshes the reverse order hit
    # a 10+ s first frame (see the module docstring); kept as a precaution.
    renderer = rendering.OffscreenRenderer(width, height)

    # The tensor-based mesh: the legacy o3d.geometry.TriangleMesh path made
    # some meshes (e.g. a marching-cubes ball of radius 9 voxels) take 20-100 s
    # per frame instead of 0.1 s (see the module docstring).
    tri = o3d.t.geometry.TriangleMesh()
    tri.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(req["vertices"], np.float32))
    tri.vertex.normals = o3d.core.Tensor(np.ascontiguousarray(req["normals"], np.float32))
    tri.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(req["faces"], np.int32))
    sun_lux, ibl, roughness, reflectance = (float(x) for x in req["light"])
    material = rendering.MaterialRecord()
    material.shader = "defaultLit"
    material.base_color = [*(float(c) for c in req["base_color"]), 1.0]
    material.base_metallic = 0.0
    material.base_roughness = roughness
    material.base_reflectance = reflectance

    scene = renderer.scene
    scene.add_geometry("mesh", tri, material)
    scene.set_background([*(float(c) for c in req["background_srgb"]), 1.0])
    scene.view.set_post_processing(False)
    scene.view.set_shadowing(False)  # a headlight casts no visible shadow
    scene.scene.enable_indirect_light(True)
    scene.scene.set_indirect_light_intensity(ibl)
    scene.scene.enable_sun_light(True)

    fov, near, far = (float(x) for x in req["camera"])
    up = np.asarray(req["up"], dtype=np.float32)
    centre = np.zeros(3, dtype=np.float32)
    images = np.empty((len(req["eyes"]), height, width, 3), dtype=np.uint8)
    for k, (eye, light_dir) in enumerate(zip(req["eyes"], req["light_dirs"], strict=True)):
        renderer.setup_camera(fov, centre, eye.astype(np.float32), up, near, far)
        scene.scene.set_sun_light(
            light_dir.astype(np.float32), np.ones(3, dtype=np.float32), sun_lux
        )
        images[k] = np.asarray(renderer.render_to_image())[:, :, :3]
    encoded = io.BytesIO()
    np.save(encoded, images, allow_pickle=False)
    with os.fdopen(out_fd, "wb") as out:  # a pipe: not seekable, so write the bytes
        out.write(encoded.getvalue())
    return 0


if __name__ == "__main__":
    _code = _worker_main()
    sys.stderr.flush()
    os._exit(_code)  # skip Filament's teardown: the images are already written
