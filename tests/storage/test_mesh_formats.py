"""Meshes for every viewer: VTK PolyData and STL in LPS lie on the mask (issue 12)."""

from __future__ import annotations

import meshio
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from tumor3d.geometry.mesh import Mesh
from tumor3d.geometry.surface import extract_surface
from tumor3d.storage.formats import encode_ply, encode_stl, encode_vtk_polydata, ras_to_lps

LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def oblique_affine():
    """(x, y, z) voxel index -> RAS: rotated, anisotropic, a flipped axis, off-centre."""
    a = np.deg2rad(25.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    aff = np.eye(4)
    aff[:3, :3] = rot @ np.diag([-0.9, 0.8, 2.5])
    aff[:3, 3] = [35.0, -20.0, 12.0]
    return aff


def ball_mask(shape=(14, 40, 44), center_zyx=(6.0, 17.0, 25.0), radius_vox=(4.5, 11.0, 12.0)):
    zz, yy, xx = np.indices(shape)
    c, r = np.asarray(center_zyx), np.asarray(radius_vox)
    return ((zz - c[0]) / r[0]) ** 2 + ((yy - c[1]) / r[1]) ** 2 + ((xx - c[2]) / r[2]) ** 2 <= 1


def mask_value_at_lps(points_lps, mask, affine_ras):
    """Trilinear mask value at LPS points, through the LPS affine of the mask's grid."""
    lps_affine = LPS_FROM_RAS @ affine_ras
    inv = np.linalg.inv(lps_affine)
    xyz = points_lps @ inv[:3, :3].T + inv[:3, 3]
    return map_coordinates(mask.astype(float), xyz[:, ::-1].T, order=1, mode="constant")


def read_mesh(path):
    """Load a mesh as a viewer would: VTK's reader for .vtk (ITK-SNAP, ParaView), else meshio."""
    if path.suffix == ".vtk":
        from vtkmodules.util.numpy_support import vtk_to_numpy
        from vtkmodules.vtkIOLegacy import vtkPolyDataReader

        reader = vtkPolyDataReader()
        reader.SetFileName(str(path))
        reader.Update()
        assert reader.IsFilePolyData()
        poly = reader.GetOutput()
        points = vtk_to_numpy(poly.GetPoints().GetData()).astype(float)
        faces = vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3)
        return points, faces
    m = meshio.read(path)
    return np.asarray(m.points, dtype=float), m.cells_dict["triangle"]


def signed_volume(vertices, faces):
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6.0)


@pytest.fixture(scope="module")
def case():
    mask, affine = ball_mask(), oblique_affine()
    return mask, affine, extract_surface(mask, affine)


def test_ras_to_lps_negates_x_and_y():
    np.testing.assert_array_equal(ras_to_lps([[1.0, 2.0, 3.0]]), [[-1.0, -2.0, 3.0]])


@pytest.mark.parametrize(
    ("encode", "suffix"), [(encode_vtk_polydata, ".vtk"), (encode_stl, ".stl")]
)
def test_lps_mesh_lies_on_the_mask_in_lps(tmp_path, case, encode, suffix):
    mask, affine, mesh = case
    f = tmp_path / f"tumor_lps{suffix}"
    f.write_bytes(encode(mesh))
    points, faces = read_mesh(f)
    assert len(faces) == mesh.n_faces
    # every vertex on the 0.5 level set of the mask, read in the viewer's LPS convention
    values = mask_value_at_lps(points, mask, affine)
    np.testing.assert_allclose(values, 0.5, atol=2e-3)
    # the same points taken as RAS (the convention error) are off the surface
    wrong = mask_value_at_lps(ras_to_lps(points), mask, affine)
    assert np.mean(np.abs(wrong - 0.5) > 0.1) > 0.9
    # outward winding kept, and the enclosed volume is the mesh's
    vol = signed_volume(points, faces)
    assert vol > 0
    assert vol == pytest.approx(signed_volume(mesh.vertices, mesh.faces), rel=1e-5)


def test_vtk_file_is_polydata_and_deterministic(case):
    _, _, mesh = case
    data = encode_vtk_polydata(mesh)
    header = data[:200].split(b"\n")
    assert header[0].startswith(b"# vtk DataFile Version 4.2")
    assert header[1] == b"tumor3d mesh, SPACE=LPS, units mm"
    assert b"DATASET POLYDATA" in data[:200]
    assert encode_vtk_polydata(mesh) == data
    stl = encode_stl(mesh)
    assert stl[:9] == b"SPACE=LPS" and encode_stl(mesh) == stl
    assert len(stl) == 84 + 50 * mesh.n_faces  # binary STL: header, count, 50 bytes a facet


def test_ras_option_writes_the_ply_coordinates(tmp_path, case):
    _, _, mesh = case
    f = tmp_path / "tumor_ras.vtk"
    f.write_bytes(encode_vtk_polydata(mesh, space="RAS"))
    ply = tmp_path / "tumor.ply"
    ply.write_bytes(encode_ply(mesh))
    np.testing.assert_allclose(read_mesh(f)[0], meshio.read(ply).points, atol=1e-5)
    with pytest.raises(ValueError, match="space must be 'LPS' or 'RAS'"):
        encode_stl(mesh, space="ras")


def test_empty_mesh_encodes():
    empty = Mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    assert b"POLYDATA" in encode_vtk_polydata(empty)
    assert len(encode_stl(empty)) == 84
