"""Byte codecs for meshes (PLY, VTK, STL), tables (parquet) and images (PNG).

Every encoder is deterministic: the same input gives the same bytes, so an
artifact's digest depends only on its content. Decoders never unpickle.

Meshes for every viewer
-----------------------
A `Mesh` holds RAS millimetres. 3D Slicer reads the PLY (its ``SPACE=RAS``
comment); ITK-SNAP and ParaView (like ITK and DICOM) work in **LPS**:
``(x, y, z)_LPS = (-x, -y, z)_RAS``. :func:`encode_vtk_polydata` writes
legacy VTK PolyData in LPS (``tumor_lps.vtk``), :func:`encode_stl` binary STL
in LPS by default (Slicer's own STL convention, with ``SPACE=LPS`` in the
header, which Slicer reads). Both go through VTK's own writers
(``vtkPolyDataWriter``, file version 4.2 so that VTK 6-9 read it;
``vtkSTLWriter``). Negating x and y is a rotation by 180 degrees about the
superior axis (determinant +1), so the faces keep their outward winding.
"""

from __future__ import annotations

import io
import re
import struct
import tempfile
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from PIL import Image

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh

__all__ = [
    "PNG_ZLIB_LEVEL",
    "UNIT_SUFFIXES",
    "decode_parquet",
    "decode_ply",
    "decode_png",
    "encode_parquet",
    "encode_ply",
    "encode_png",
    "encode_stl",
    "encode_vtk_polydata",
    "ras_to_lps",
]

_PLY_HEADER = (
    "ply\n"
    "format binary_little_endian 1.0\n"
    "comment SPACE=RAS\n"
    "comment units: millimetres; written by tumor3d\n"
    "element vertex {nv}\n"
    "property float x\n"
    "property float y\n"
    "property float z\n"
    "element face {nf}\n"
    "property list uchar int vertex_indices\n"
    "end_header\n"
)
_FACE_DTYPE = np.dtype([("n", "u1"), ("v", "<i4", (3,))])


def encode_ply(mesh: Mesh) -> bytes:
    """Encode a triangle mesh as binary little-endian PLY.

    Vertices are stored as float32 RAS millimetres. The header carries the
    comment ``SPACE=RAS``, which 3D Slicer reads so that the mesh overlays
    the image without a flip (Slicer otherwise assumes LPS).
    """
    header = _PLY_HEADER.format(nv=mesh.n_vertices, nf=mesh.n_faces).encode("ascii")
    verts = np.ascontiguousarray(mesh.vertices, dtype="<f4")
    faces = np.empty(mesh.n_faces, dtype=_FACE_DTYPE)
    faces["n"] = 3
    faces["v"] = mesh.faces
    return header + verts.tobytes() + faces.tobytes()


def decode_ply(data: bytes, *, name: str = "<ply>") -> Mesh:
    """Decode the binary PLY written by :func:`encode_ply` (triangles only)."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise InputError("not a PLY file", path=name)
    header = data[:end].decode("ascii", errors="replace")
    if "format binary_little_endian 1.0" not in header:
        raise InputError("only binary little-endian PLY is supported", path=name)
    nv = re.search(r"element vertex (\d+)", header)
    nf = re.search(r"element face (\d+)", header)
    if nv is None or nf is None:
        raise InputError("PLY header lacks vertex or face counts", path=name)
    n_vertices, n_faces = int(nv.group(1)), int(nf.group(1))
    body = memoryview(data)[end + len(b"end_header\n") :]
    vbytes = n_vertices * 12
    if len(body) != vbytes + n_faces * _FACE_DTYPE.itemsize:
        raise InputError("PLY body size does not match its header", path=name)
    verts = np.frombuffer(body[:vbytes], dtype="<f4").reshape(n_vertices, 3)
    faces = np.frombuffer(body[vbytes:], dtype=_FACE_DTYPE)
    if n_faces and not np.all(faces["n"] == 3):
        raise InputError("PLY holds non-triangular faces", path=name)
    return Mesh(verts.astype(np.float64), faces["v"].astype(np.int64))


_RAS_LPS = np.array([-1.0, -1.0, 1.0])


def ras_to_lps(points_mm: np.ndarray) -> np.ndarray:
    """Convert ``(n, 3)`` points between RAS and LPS mm (negate x and y; its own inverse)."""
    pts = np.asarray(points_mm, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {pts.shape}")
    return pts * _RAS_LPS


def _vtk_polydata(mesh: Mesh, space: str) -> object:
    from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

    verts = mesh.vertices if space == "RAS" else ras_to_lps(mesh.vertices)
    points = vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(verts, dtype=np.float32), deep=True))
    offsets = np.arange(0, 3 * mesh.n_faces + 1, 3, dtype=np.int64)
    connectivity = np.ascontiguousarray(mesh.faces, dtype=np.int64).ravel()
    cells = vtkCellArray()
    cells.SetData(
        numpy_to_vtkIdTypeArray(offsets, deep=True),
        numpy_to_vtkIdTypeArray(connectivity, deep=True),
    )
    poly = vtkPolyData()
    poly.SetPoints(points)
    poly.SetPolys(cells)
    return poly


def _write_with(writer: object, suffix: str) -> bytes:
    with tempfile.TemporaryDirectory(prefix="tumor3d-mesh-") as tmp:
        path = Path(tmp) / f"mesh{suffix}"
        writer.SetFileName(str(path))  # type: ignore[attr-defined]
        if not writer.Write():  # type: ignore[attr-defined]
            raise OSError(f"VTK could not write a {suffix} mesh")
        return path.read_bytes()


def _check_space(space: str) -> str:
    if space not in ("LPS", "RAS"):
        raise ValueError(f"space must be 'LPS' or 'RAS', got {space!r}")
    return space


def encode_vtk_polydata(mesh: Mesh, *, space: str = "LPS") -> bytes:
    """Encode a triangle mesh as binary legacy VTK PolyData (``tumor_lps.vtk``).

    Parameters
    ----------
    mesh : Mesh
        Vertices in RAS mm.
    space : {"LPS", "RAS"}
        Coordinates written: LPS (default; ITK-SNAP, ParaView, ITK) has
        ``x_LPS = -x_RAS, y_LPS = -y_RAS``.

    Returns
    -------
    bytes
        A ``.vtk`` file (``DATASET POLYDATA``, float32 points, triangles),
        header line ``tumor3d mesh, SPACE=<space>, units mm``.
    """
    from vtkmodules.vtkIOLegacy import vtkPolyDataWriter

    sp = _check_space(space)
    writer = vtkPolyDataWriter()
    writer.SetInputData(_vtk_polydata(mesh, sp))
    writer.SetFileTypeToBinary()
    writer.SetFileVersion(42)
    writer.SetHeader(f"tumor3d mesh, SPACE={sp}, units mm")
    return _write_with(writer, ".vtk")


def encode_stl(mesh: Mesh, *, space: str = "LPS") -> bytes:
    """Encode a triangle mesh as binary STL.

    STL has no coordinate system; 3D Slicer reads ``SPACE=LPS`` or
    ``SPACE=RAS`` from the 80-byte header (and assumes LPS without it),
    which is written here.

    Parameters
    ----------
    mesh : Mesh
        Vertices in RAS mm.
    space : {"LPS", "RAS"}
        Coordinates written (default LPS, Slicer's STL convention).

    Returns
    -------
    bytes
        A binary ``.stl`` file (float32 facet normals and vertices).
    """
    from vtkmodules.vtkIOGeometry import vtkSTLWriter

    sp = _check_space(space)
    writer = vtkSTLWriter()
    writer.SetInputData(_vtk_polydata(mesh, sp))
    writer.SetFileTypeToBinary()
    writer.SetHeader(f"SPACE={sp} tumor3d mesh, units mm")
    return _write_with(writer, ".stl")


#: Name endings of columns that hold a number in a unit (the project's names say the unit:
#: ``outline_shift_mm``, ``volume_eq7_ml``, ``time_flow_s``).
UNIT_SUFFIXES = ("_mm", "_mm2", "_mm3", "_ml", "_s")


def encode_parquet(table: pd.DataFrame) -> bytes:
    """Encode a data frame as parquet bytes (no index, deterministic).

    A column named with a unit (:data:`UNIT_SUFFIXES`) whose every value is empty
    (None) is written as float64 NaN, as it is in a table where another row has a
    value: ``metrics.parquet``'s one row and a cohort's many give it one type.

    >>> t = decode_parquet(encode_parquet(pd.DataFrame([{"outline_shift_mm": None,
    ...                                                  "notes": None}])))
    >>> str(t["outline_shift_mm"].dtype), t["notes"].tolist()
    ('float64', [None])
    """
    empty_units = [
        c
        for c in table.columns
        if isinstance(c, str)
        and c.endswith(UNIT_SUFFIXES)
        and table[c].dtype == object
        and table[c].isna().all()
    ]
    if empty_units:
        table = table.astype({c: "float64" for c in empty_units})
    arrow = pa.Table.from_pandas(table, preserve_index=False)
    arrow = arrow.replace_schema_metadata(None)
    sink = io.BytesIO()
    pq.write_table(arrow, sink, compression="zstd", write_statistics=False)
    return sink.getvalue()


def decode_parquet(data: bytes) -> pd.DataFrame:
    """Decode parquet bytes into a data frame."""
    return pq.read_table(io.BytesIO(data)).to_pandas()


#: zlib level of :func:`encode_png`: 2 of 9, about 5 times faster than Pillow's default (6)
#: on the overlays and renders for 9-18 % more bytes (reports/benchmarks.md, "Cohort flow").
PNG_ZLIB_LEVEL = 2
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_COLOUR_TYPE = {1: 0, 3: 2, 4: 6}  # channels -> greyscale, RGB, RGBA
_PNG_FILTER_UP = 2


def _png_chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))


def encode_png(rgb: np.ndarray) -> bytes:
    """Encode an ``(h, w, 3)`` or ``(h, w)`` uint8 image as PNG (also ``(h, w, 4)``: RGBA).

    8 bits a sample, not interlaced, every row with the PNG "Up" filter (the
    row minus the row above, modulo 256; one numpy subtraction, where
    Pillow tries five filters a row) and deflated at zlib level
    :data:`PNG_ZLIB_LEVEL`. Any PNG reader gives back exactly these pixels.
    """
    arr = np.asarray(rgb)
    channels = 1 if arr.ndim == 2 else (arr.shape[2] if arr.ndim == 3 else 0)
    if arr.dtype != np.uint8 or channels not in _PNG_COLOUR_TYPE or 0 in arr.shape:
        raise ValueError(f"PNG needs a uint8 (h, w[, 3]) array, got {arr.dtype} {arr.shape}")
    h, w = arr.shape[:2]
    rows = np.ascontiguousarray(arr).reshape(h, w * channels)
    filtered = np.empty((h, w * channels + 1), dtype=np.uint8)
    filtered[:, 0] = _PNG_FILTER_UP  # the first row's "above" is zeros: itself
    filtered[0, 1:] = rows[0]
    np.subtract(rows[1:], rows[:-1], out=filtered[1:, 1:])  # uint8 wraps modulo 256
    header = struct.pack(">IIBBBBB", w, h, 8, _PNG_COLOUR_TYPE[channels], 0, 0, 0)
    return (
        _PNG_SIGNATURE
        + _png_chunk(b"IHDR", header)
        + _png_chunk(b"IDAT", zlib.compress(filtered.tobytes(), PNG_ZLIB_LEVEL))
        + _png_chunk(b"IEND", b"")
    )


def decode_png(data: bytes) -> np.ndarray:
    """Decode PNG bytes into a uint8 array."""
    with Image.open(io.BytesIO(data)) as img:
        return np.asarray(img.convert("RGB"))
