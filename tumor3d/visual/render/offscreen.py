"""The Open3D renderer: Open3D's offscreen Filament renderer in a child process.

Both sides of the pipe: the scene as flat arrays (:func:`_open3d_request`)
and the child's start (:func:`_run_worker`) in the calling process, and
the child's own entry (:func:`_worker_main`, run by ``python -m
tumor3d.visual.render``: :mod:`tumor3d.visual.render.__main__`), the only
code that imports Open3D. See "Design: one subprocess per call" in
:mod:`tumor3d.visual.render`.
"""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from tumor3d.visual.render.camera import Camera

# Filament calibration (measured, open3d 0.20): a directional light of
# 100 000 lux gives a radiance of 0.47 x the albedo on a surface facing it
# (Open3D's default camera exposure), and the default image-based light at
# 30 000 gives 0.47 on average.
_SUN_LUX_PER_UNIT = 100_000.0 / 0.47


_IBL_PER_UNIT = 30_000.0 / 0.47


def _open3d_request(scene: dict[str, Any], lighting: np.ndarray) -> dict[str, np.ndarray]:
    """The scene as flat arrays for the child, vertices centred for float32 precision."""
    cams: list[Camera] = scene["cameras"]
    centre = cams[0].centre
    radius = scene["radius"]
    k_a, k_d, k_s, s = (float(x) for x in lighting)
    req: dict[str, np.ndarray] = {}
    for i, g in enumerate(scene["geoms"]):
        req[f"g{i}_vertices"] = np.asarray(g["vertices"] - centre, dtype=np.float32)
        req[f"g{i}_normals"] = np.asarray(g["normals"], dtype=np.float32)
        req[f"g{i}_faces"] = np.asarray(g["faces"], dtype=np.int32)
        req[f"g{i}_color"] = np.array([*g["color"], g["opacity"]])
    vis = np.zeros((len(cams), len(scene["geoms"])), dtype=bool)
    for k, v in enumerate(scene["visible"]):
        vis[k, v] = True
    w, h = scene["size"]
    half_w = w / 2.0 / cams[0].pixels_per_mm
    half_h = h / 2.0 / cams[0].pixels_per_mm
    dist = 3.0 * radius
    req.update(
        n_geoms=np.array(len(scene["geoms"])),
        visible=vis,
        forward=np.array([c.forward for c in cams]),
        up=np.array([c.up for c in cams]),
        size=np.array([w, h], dtype=np.int64),
        # left, right, bottom, top, near, far, eye distance
        ortho=np.array(
            [-half_w, half_w, -half_h, half_h, dist - 1.5 * radius, dist + 1.5 * radius, dist]
        ),
        background_srgb=_srgb_encode(scene["background"]),
        # sun illuminance, ambient (image-based light) intensity, roughness, reflectance
        light=np.array(
            [
                k_d * _SUN_LUX_PER_UNIT,
                k_a * _IBL_PER_UNIT,
                (2.0 / (s + 2.0)) ** 0.25,
                min(1.0, 0.5 * k_s / 0.3),
            ]
        ),
    )
    return req


def _srgb_encode(c: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)


def _run_worker(request: dict[str, np.ndarray], timeout_s: float) -> np.ndarray:
    """Render in a child process; return the stacked ``(k, h, w, 3)`` images."""
    buf = io.BytesIO()
    np.savez(buf, **request)
    env = dict(os.environ)
    # the folder holding tumor3d/ (this file is tumor3d/visual/render/offscreen.py)
    package_root = str(Path(__file__).resolve().parents[3])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH", "")) if p)
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "tumor3d.visual.render"],
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
    "GLFWWindowSystem",
)


def _error_tail(stderr: bytes, n_lines: int = 20) -> str:
    lines = [
        ln
        for ln in stderr.decode("utf-8", errors="replace").splitlines()
        if ln.strip() and not any(tok in ln for tok in _NOISE)
    ]
    return "\n".join(lines[-n_lines:]) or "(no error output)"


def _worker_main() -> int:
    """Entry point of ``python -m tumor3d.visual.render``: stdin request -> stdout images."""
    out_fd = os.dup(1)  # private copy of the real stdout, for the images only
    os.dup2(2, 1)  # Filament prints on stdout: divert everything else to stderr
    sys.stdout = sys.stderr
    payload = sys.stdin.buffer.read()
    with np.load(io.BytesIO(payload), allow_pickle=False) as data:
        req = {k: data[k] for k in data.files}
    if os.environ.get("TUMOR3D_RENDER_FAIL"):  # test hook: simulate a broken driver
        raise RuntimeError("TUMOR3D_RENDER_FAIL is set: simulated renderer failure")

    import open3d as o3d  # only ever imported in the child

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    rendering = o3d.visualization.rendering
    width, height = (int(x) for x in req["size"])
    # Renderer first, geometry after (see :mod:`tumor3d.visual.render`).
    renderer = rendering.OffscreenRenderer(width, height)
    scene = renderer.scene
    sun_lux, ibl, roughness, reflectance = (float(x) for x in req["light"])
    n_geoms = int(req["n_geoms"])
    for i in range(n_geoms):
        tri = o3d.t.geometry.TriangleMesh()
        tri.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(req[f"g{i}_vertices"]))
        tri.vertex.normals = o3d.core.Tensor(np.ascontiguousarray(req[f"g{i}_normals"]))
        tri.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(req[f"g{i}_faces"]))
        rgba = [float(c) for c in req[f"g{i}_color"]]
        material = rendering.MaterialRecord()
        material.shader = "defaultLit" if rgba[3] >= 1.0 else "defaultLitTransparency"
        material.base_color = rgba
        material.base_metallic = 0.0
        material.base_roughness = roughness
        material.base_reflectance = reflectance
        scene.add_geometry(f"g{i}", tri, material)
    scene.set_background([*(float(c) for c in req["background_srgb"]), 1.0])
    scene.view.set_post_processing(False)
    scene.view.set_shadowing(False)  # a headlight casts no visible shadow
    scene.scene.enable_indirect_light(True)
    scene.scene.set_indirect_light_intensity(ibl)
    scene.scene.enable_sun_light(True)

    left, right, bottom, top, near, far, dist = (float(x) for x in req["ortho"])
    camera = scene.camera
    camera.set_projection(rendering.Camera.Projection.Ortho, left, right, bottom, top, near, far)
    visible = req["visible"]
    shown = [True] * n_geoms
    images = np.empty((len(visible), height, width, 3), dtype=np.uint8)
    for k in range(len(visible)):
        for i in range(n_geoms):
            if bool(visible[k, i]) != shown[i]:
                scene.show_geometry(f"g{i}", bool(visible[k, i]))
                shown[i] = bool(visible[k, i])
        fwd = req["forward"][k].astype(np.float32)
        camera.look_at(np.zeros(3, np.float32), -dist * fwd, req["up"][k].astype(np.float32))
        scene.scene.set_sun_light(fwd, np.ones(3, dtype=np.float32), sun_lux)
        images[k] = np.asarray(renderer.render_to_image())[:, :, :3]
    encoded = io.BytesIO()
    np.save(encoded, images, allow_pickle=False)
    with os.fdopen(out_fd, "wb") as out:  # a pipe: not seekable, so write the bytes
        out.write(encoded.getvalue())
    return 0
