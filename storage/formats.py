"""Byte codecs for meshes (PLY), tables (parquet) and images (PNG).

Every encoder is deterministic: the same input gives the same bytes, so an
artifact's digest depends only on its content. Decoders never unpickle.
"""

from __future__ import annotations

import io
import re

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from PIL import Image

from tumor3d.errors import InputError
from tumor3d.mesh import Mesh

__all__ = [
    "decode_parquet",
    "decode_ply",
    "decode_png",
    "encode_parquet",
    "encode_ply",
    "encode_png",
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


def encode_parquet(table: pd.DataFrame) -> bytes:
    """Encode a data frame as parquet bytes (no index, deterministic)."""
    arrow = pa.Table.from_pandas(table, preserve_index=False)
    arrow = arrow.replace_schema_metadata(None)
    sink = io.BytesIO()
    pq.write_table(arrow, sink, compression="zstd", write_statistics=False)
    return sink.getvalue()


def decode_parquet(data: bytes) -> pd.DataFrame:
    """Decode parquet bytes into a data frame."""
    return pq.read_table(io.BytesIO(data)).to_pandas()


def encode_png(rgb: np.ndarray) -> bytes:
    """Encode an ``(h, w, 3)`` or ``(h, w)`` uint8 image as PNG."""
    arr = np.asarray(rgb)
    if arr.dtype != np.uint8 or arr.ndim not in (2, 3):
        raise ValueError(f"PNG needs a uint8 (h, w[, 3]) array, got {arr.dtype} {arr.shape}")
    sink = io.BytesIO()
    Image.fromarray(arr).save(sink, format="PNG", optimize=False)
    return sink.getvalue()


def decode_png(data: bytes) -> np.ndarray:
    """Decode PNG bytes into a uint8 array."""
    with Image.open(io.BytesIO(data)) as img:
        return np.asarray(img.convert("RGB"))
