"""Tests of tumor3d.geometry.surface: marching cubes, cleaning, volume/area, edge topology."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage as ndi

from tumor3d.errors import InputError, NoSurfaceError
from tumor3d.geometry.mesh import Mesh
from tumor3d.geometry.surface import (
    clean_mesh,
    edge_manifold_report,
    extract_surface,
    is_watertight,
    mesh_area_mm2,
    mesh_volume_mm3,
    orient_outward,
)

# ---------------------------------------------------------------------------
# phantoms
# ---------------------------------------------------------------------------


def ellipsoid_mask(spacing_zyx, radii_xyz_mm, *, shape=None, centre_zyx=None):
    """Voxelised ellipsoid: voxel centres inside ((x/rx)^2 + (y/ry)^2 + (z/rz)^2 <= 1)."""
    dz, dy, dx = spacing_zyx
    rx, ry, rz = radii_xyz_mm
    if shape is None:
        shape = tuple(int(2 * r / s) + 6 for r, s in zip((rz, ry, rx), (dz, dy, dx), strict=True))
    if centre_zyx is None:
        centre_zyx = tuple((k - 1) / 2 + 0.3 for k in shape)  # off-grid centre
    z, y, x = np.ogrid[: shape[0], : shape[1], : shape[2]]
    cz, cy, cx = centre_zyx
    inside = ((x - cx) * dx / rx) ** 2 + ((y - cy) * dy / ry) ** 2 + ((z - cz) * dz / rz) ** 2
    return inside <= 1.0, np.array(centre_zyx)


def diag_affine(spacing_zyx, origin_xyz=(0.0, 0.0, 0.0)):
    dz, dy, dx = spacing_zyx
    aff = np.diag([dx, dy, dz, 1.0])
    aff[:3, 3] = origin_xyz
    return aff


def rotation(axis, angle_rad):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * k @ k


def volume_centroid(mesh):
    """Centroid of the enclosed solid (divergence theorem on signed tetrahedra)."""
    v, f = mesh.vertices, mesh.faces
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    return ((a + b + c) / 4.0 * vol[:, None]).sum(axis=0) / vol.sum()


CUBE_V = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    dtype=float,
)
CUBE_F = np.array(
    [
        [0, 2, 1], [0, 3, 2],  # z = 0, normal -z
        [4, 5, 6], [4, 6, 7],  # z = 1, normal +z
        [0, 1, 5], [0, 5, 4],  # y = 0, normal -y
        [2, 3, 7], [2, 7, 6],  # y = 1, normal +y
        [1, 2, 6], [1, 6, 5],  # x = 1, normal +x
        [0, 4, 7], [0, 7, 3],  # x = 0, normal -x
    ]
)  # fmt: skip


# ---------------------------------------------------------------------------
# measurements on hand-made meshes
# ---------------------------------------------------------------------------


def test_unit_cube_volume_area_and_watertight():
    cube = Mesh(CUBE_V, CUBE_F)
    assert mesh_volume_mm3(cube) == pytest.approx(1.0, abs=1e-12)
    assert mesh_area_mm2(cube) == pytest.approx(6.0, abs=1e-12)
    assert is_watertight(cube)
    flipped = Mesh(CUBE_V, CUBE_F[:, ::-1])
    assert mesh_volume_mm3(flipped) == pytest.approx(-1.0, abs=1e-12)
    # closed mesh: volume does not depend on the origin
    moved = Mesh(CUBE_V * [2.0, 3.0, 0.5] + [100.0, -50.0, 7.0], CUBE_F)
    assert mesh_volume_mm3(moved) == pytest.approx(3.0, rel=1e-12)


def test_orient_outward_flips_only_inward_meshes():
    cube = Mesh(CUBE_V, CUBE_F)
    assert orient_outward(cube) is cube
    fixed = orient_outward(Mesh(CUBE_V, CUBE_F[:, ::-1]))
    assert mesh_volume_mm3(fixed) == pytest.approx(1.0)
    assert is_watertight(fixed)


def test_is_watertight_detects_removed_and_flipped_face():
    cube = Mesh(CUBE_V, CUBE_F)
    holed = Mesh(CUBE_V, CUBE_F[1:])
    assert not is_watertight(holed)
    assert edge_manifold_report(holed)["n_boundary_edges"] == 3
    faces = CUBE_F.copy()
    faces[5] = faces[5, ::-1]
    flipped_one = Mesh(CUBE_V, faces)
    assert not is_watertight(flipped_one)
    assert edge_manifold_report(flipped_one)["n_inconsistent_edges"] == 3
    assert is_watertight(cube)


def test_edge_report_counts_nonmanifold_and_degenerate():
    # three triangles sharing edge (0, 1): one non-manifold edge
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [0, 0, 2]])
    r = edge_manifold_report(Mesh(v, f))
    assert r["n_nonmanifold_edges"] == 1
    assert r["n_degenerate_faces"] == 1
    assert not is_watertight(Mesh(v, f))
    assert not is_watertight(Mesh(np.zeros((0, 3)), np.zeros((0, 3), int)))


def _naive_edge_report(faces):
    uses = {}
    for a, b, c in faces.tolist():
        for p, q in ((a, b), (b, c), (c, a)):
            uses.setdefault((min(p, q), max(p, q)), []).append(p < q)
    return {
        "n_edges": len(uses),
        "n_boundary_edges": sum(len(u) == 1 for u in uses.values()),
        "n_nonmanifold_edges": sum(len(u) > 2 for u in uses.values()),
        "n_inconsistent_edges": sum(len(u) == 2 and u[0] == u[1] for u in uses.values()),
    }


@pytest.mark.parametrize("seed", range(5))
def test_edge_report_matches_naive_reference(seed):
    rng = np.random.default_rng(seed)
    n_v = 12
    faces = np.array([rng.choice(n_v, 3, replace=False) for _ in range(40)])
    # include a real closed piece so that all categories occur
    faces = np.concatenate([faces, CUBE_F + n_v, CUBE_F[:3, ::-1] + n_v])
    verts = rng.normal(size=(n_v + 8, 3))
    got = edge_manifold_report(Mesh(verts, faces))
    want = _naive_edge_report(faces)
    assert {k: got[k] for k in want} == want


def test_clean_mesh_cancels_opposite_pairs_and_dedups_same_orientation():
    extra_v = np.vstack([CUBE_V, [[0.5, 0.5, 2.0]]])  # vertex 8, used only by the sheet
    sheet = np.array([[4, 5, 8], [5, 4, 8]])  # a back-to-back double sheet
    same = CUBE_F[:2]  # same-orientation duplicates
    dirty = Mesh(extra_v, np.concatenate([CUBE_F, sheet, same, [[1, 1, 2]]]))
    assert not is_watertight(dirty)
    cleaned = clean_mesh(dirty)
    assert is_watertight(cleaned)
    assert cleaned.n_faces == 12 and cleaned.n_vertices == 8  # vertex 8 dropped
    assert mesh_volume_mm3(cleaned) == pytest.approx(1.0)


def test_clean_mesh_welds_identical_vertices_only_when_asked():
    # the cube with vertex 0 duplicated (faces of the x = 0 side use the copy)
    v = np.vstack([CUBE_V, CUBE_V[:1]])
    f = CUBE_F.copy()
    f[10:] = np.where(f[10:] == 0, 8, f[10:])
    split = Mesh(v, f)
    assert not is_watertight(split)
    assert is_watertight(clean_mesh(split))
    assert not is_watertight(clean_mesh(split, weld=False))


# ---------------------------------------------------------------------------
# marching cubes on analytic phantoms
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("spacing", "radii"),
    [((2.0, 0.9, 0.8), (12.0, 12.0, 12.0)), ((2.0, 0.9, 0.8), (14.0, 10.0, 12.0))],
)
def test_ellipsoid_volume_and_topology(spacing, radii):
    mask, _ = ellipsoid_mask(spacing, radii)
    mesh = extract_surface(mask, diag_affine(spacing))
    assert is_watertight(mesh)
    vol = mesh_volume_mm3(mesh)
    assert vol > 0
    voxel_vol = mask.sum() * np.prod(spacing)
    analytic = 4.0 / 3.0 * np.pi * np.prod(radii)
    # measured: -0.5 % vs voxels, -0.55 to -0.7 % vs analytic
    assert abs(vol / voxel_vol - 1) < 0.03
    assert abs(vol / analytic - 1) < 0.03
    # the surface lies between the inner and outer voxel faces: extents match 2 r
    extent = np.ptp(mesh.vertices, axis=0)
    dz, dy, dx = spacing
    np.testing.assert_allclose(extent, 2 * np.array(radii), atol=max(dx, dy, dz))


def test_vertices_in_ras_with_rotated_translated_affine():
    spacing = (2.0, 0.9, 0.8)
    mask, centre_zyx = ellipsoid_mask(spacing, (12.0, 9.0, 10.0))
    aff = np.eye(4)
    aff[:3, :3] = rotation([1.0, 2.0, 0.5], 0.7) @ np.diag([0.8, 0.9, 2.0])
    aff[:3, 3] = [-90.0, 120.0, -30.0]
    mesh = extract_surface(mask, aff)
    assert is_watertight(mesh)
    # the RAS centre from the affine, computed independently: A @ (x, y, z, 1)
    cz, cy, cx = centre_zyx
    expected = (aff @ [cx, cy, cz, 1.0])[:3]
    np.testing.assert_allclose(volume_centroid(mesh), expected, atol=0.25)
    # rotation and translation do not change the volume
    plain = extract_surface(mask, diag_affine(spacing))
    assert mesh_volume_mm3(mesh) == pytest.approx(mesh_volume_mm3(plain), rel=1e-9)


def test_negative_determinant_affine_still_outward():
    spacing = (2.0, 0.9, 0.8)
    mask, _ = ellipsoid_mask(spacing, (10.0, 12.0, 11.0))
    lps = np.diag([-0.8, -0.9, 2.0, 1.0])  # an LPS-like flip of x and y: det > 0
    flip_one = np.diag([-0.8, 0.9, 2.0, 1.0])  # one flipped axis: det < 0
    flip_one[:3, 3] = [50.0, -20.0, 10.0]
    ref = mesh_volume_mm3(extract_surface(mask, diag_affine(spacing)))
    for aff in (lps, flip_one):
        mesh = extract_surface(mask, aff)
        assert is_watertight(mesh)
        assert mesh_volume_mm3(mesh) == pytest.approx(ref, rel=1e-9)
    assert np.linalg.det(flip_one) < 0


def test_mask_touching_border_is_closed_by_padding():
    block = np.ones((4, 5, 6), dtype=np.uint8)
    aff = diag_affine((2.0, 1.0, 0.5), origin_xyz=(3.0, 4.0, 5.0))
    mesh = extract_surface(block, aff)
    assert is_watertight(mesh)
    # the same block inside a larger empty array gives the same surface
    big = np.zeros((10, 11, 12), dtype=np.uint8)
    big[2:6, 3:8, 1:7] = 1
    shifted = aff.copy()
    shifted[:3, 3] -= aff[:3, :3] @ [1, 3, 2]  # index (x, y, z) offset of the block
    ref = extract_surface(big, shifted)
    assert mesh.n_faces == ref.n_faces
    assert mesh_volume_mm3(mesh) == pytest.approx(mesh_volume_mm3(ref), rel=1e-12)
    np.testing.assert_allclose(
        np.sort(mesh.vertices, axis=0), np.sort(ref.vertices, axis=0), atol=1e-9
    )
    # the surface lies half a voxel outside the outer voxel centres at most
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    np.testing.assert_allclose(lo, [3.0 - 0.25, 4.0 - 0.5, 5.0 - 1.0])
    np.testing.assert_allclose(hi, [3.0 + 2.5 + 0.25, 4.0 + 4.0 + 0.5, 5.0 + 6.0 + 1.0])


def test_single_voxel_is_an_octahedron():
    m = np.zeros((3, 3, 3), dtype=bool)
    m[1, 1, 1] = True
    mesh = extract_surface(m, diag_affine((3.0, 2.0, 1.0)))
    assert mesh.n_faces == 8 and mesh.n_vertices == 6
    # half-diagonals 0.5, 1.0, 1.5 mm: volume (4/3) * 0.5 * 1.0 * 1.5
    assert mesh_volume_mm3(mesh) == pytest.approx(1.0)


@pytest.mark.parametrize("seed", range(3))
def test_random_masks_give_watertight_outward_surfaces(seed):
    # ambiguous marching-cubes configurations everywhere; skimage's Lewiner
    # tables emit cancelling double faces on some of them (cleaned away)
    rng = np.random.default_rng(seed)
    for _ in range(30):
        shape = tuple(rng.integers(2, 9, size=3))
        mask = rng.random(shape) < rng.uniform(0.2, 0.7)
        if rng.random() < 0.3:
            mask = ndi.binary_closing(mask)
        if not mask.any():
            continue
        aff = np.eye(4)
        aff[:3, :3] = rng.normal(size=(3, 3))
        mesh = extract_surface(mask, aff)
        assert is_watertight(mesh), edge_manifold_report(mesh)
        assert mesh_volume_mm3(mesh) > 0


def test_inputs_are_not_modified():
    mask, _ = ellipsoid_mask((1.0, 1.0, 1.0), (4.0, 4.0, 4.0))
    mask = mask.astype(np.uint8)
    aff = diag_affine((1.0, 1.0, 1.0), (1.0, 2.0, 3.0))
    mask_copy, aff_copy = mask.copy(), aff.copy()
    extract_surface(mask, aff)
    np.testing.assert_array_equal(mask, mask_copy)
    np.testing.assert_array_equal(aff, aff_copy)


def test_empty_mask_raises_no_surface():
    with pytest.raises(NoSurfaceError, match="no voxel"):
        extract_surface(np.zeros((4, 4, 4), dtype=bool), np.eye(4))


# ---------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------

_GOOD = np.ones((2, 2, 2), dtype=bool)


@pytest.mark.parametrize(
    ("mask", "affine", "kwargs", "match"),
    [
        (np.ones((2, 2), bool), np.eye(4), {}, "3-D"),
        (np.ones((2, 2, 2), float), np.eye(4), {}, "bool or integer"),
        (np.full((2, 2, 2), 2, np.uint8), np.eye(4), {}, "only 0 and 1"),
        (_GOOD, np.eye(3), {}, "4x4"),
        (_GOOD, np.full((4, 4), "a"), {}, "real-valued"),
        (_GOOD, np.diag([1.0, np.nan, 1.0, 1.0]), {}, "finite"),
        (_GOOD, np.ones((4, 4)), {}, "last row"),
        (_GOOD, np.diag([1.0, 0.0, 1.0, 1.0]), {}, "singular"),
        (_GOOD, np.eye(4), {"level": "0.5"}, "level must be a number"),
        (_GOOD, np.eye(4), {"level": 1.0}, "strictly between"),
        (_GOOD, np.eye(4), {"padding": 0}, "padding"),
    ],
)
def test_extract_surface_validation(mask, affine, kwargs, match):
    with pytest.raises(InputError, match=match):
        extract_surface(mask, affine, **kwargs)


def test_measurements_reject_non_mesh():
    with pytest.raises(InputError, match="must be a tumor3d.geometry.mesh.Mesh"):
        mesh_volume_mm3((CUBE_V, CUBE_F))


# ---------------------------------------------------------------------------
# marching cubes: every cube configuration, topology and volume invariants
# ---------------------------------------------------------------------------

#: the six faces of a 2x2x2 corner block, as (z, y, x) corner index quadruples in cyclic order
_CUBE_FACES = [
    [(z, 0, 0), (z, 0, 1), (z, 1, 1), (z, 1, 0)] for z in (0, 1)
] + [[(0, y, 0), (0, y, 1), (1, y, 1), (1, y, 0)] for y in (0, 1)] + [
    [(0, 0, x), (0, 1, x), (1, 1, x), (1, 0, x)] for x in (0, 1)
]


def _block(bits, shape=(2, 2, 2)):
    n = int(np.prod(shape))
    return np.array([(bits >> k) & 1 for k in range(n)], dtype=bool).reshape(shape)


def _ambiguous_faces(block):
    """Faces whose in-corners are one diagonal only (the saddle cases of [MSS94])."""
    count = 0
    for quad in _CUBE_FACES:
        a, b, c, d = (block[q] for q in quad)
        if a == c and b == d and a != b:
            count += 1
    return count


def _vertex_fans_ok(mesh):
    nxt = {}
    for a, b, c in mesh.faces.tolist():
        for v, p, q in ((a, b, c), (b, c, a), (c, a, b)):
            d = nxt.setdefault(v, {})
            if p in d:
                return False
            d[p] = q
    for d in nxt.values():
        start = next(iter(d))
        cur, steps = d[start], 1
        while cur != start and cur in d and steps <= len(d):
            cur, steps = d[cur], steps + 1
        if cur != start or steps != len(d):
            return False
    return True


def test_every_cube_configuration_gives_a_closed_oriented_manifold():
    # All 255 non-empty in/out patterns of one cube's 8 corners. They include
    # Lorensen-Cline cases 3, 6, 7, 10, 12, 13 (one, one, three, two, two and six
    # ambiguous faces) and their complements, which Montani's 21-case table
    # resolves by a fixed rule and Lewiner's MC33 tables by face/interior tests.
    # Each block is zero-padded, so its ambiguous faces are shared with the
    # neighbouring cubes, which must agree with it for the surface to close.
    seen = set()
    for bits in range(1, 256):
        block = _block(bits)
        seen.add(_ambiguous_faces(block))
        mesh = extract_surface(block, np.eye(4))
        r = edge_manifold_report(mesh)
        assert is_watertight(mesh), (bits, r)
        assert r["n_duplicate_faces"] == 0, bits
        assert mesh_volume_mm3(mesh) > 0, bits
        assert _vertex_fans_ok(mesh), bits
        # Euler characteristic of closed orientable surfaces: 2 - 2 genus per
        # component, and at most one component per 6-connected voxel group
        # (MC33 may join diagonal voxels, e.g. into a torus: chi = 0)
        n_comp = ndi.label(block, structure=ndi.generate_binary_structure(3, 1))[1]
        chi = np.unique(mesh.faces).size - r["n_edges"] + r["n_faces"]
        assert chi % 2 == 0 and chi <= 2 * n_comp, (bits, chi, n_comp)
    assert {1, 2, 3, 6} <= seen  # the ambiguous-face counts of cases 3/6, 10/12, 7, 13


def test_every_pair_of_adjacent_cubes_closes():
    # 2x2x3 corners = two cubes sharing one face: all 4095 non-empty patterns,
    # so every combination of configurations on the two sides of a face (ambiguous
    # or not) is met
    for bits in range(1, 4096):
        mesh = extract_surface(_block(bits, (2, 2, 3)), np.eye(4))
        assert is_watertight(mesh), bits
        assert mesh_volume_mm3(mesh) > 0, bits


@pytest.mark.parametrize("radius_vox", [4.0, 8.0, 20.0])
def test_ball_has_euler_characteristic_two_and_voxel_volume(radius_vox):
    mask, _ = ellipsoid_mask((1.0, 1.0, 1.0), (radius_vox,) * 3)
    mesh = extract_surface(mask, np.eye(4))
    r = edge_manifold_report(mesh)
    assert mesh.n_vertices - r["n_edges"] + r["n_faces"] == 2
    ratio = mesh_volume_mm3(mesh) / mask.sum()
    # large shapes within 1 %, small ones within 3 % (the cut corners of the
    # marching-cubes surface are a surface effect, relative size ~ 1 / r)
    assert abs(ratio - 1) < (0.01 if radius_vox >= 20 else 0.03)


@pytest.mark.parametrize("offset_mm", [0.0, 1e4, 1e6, 1e7, 1e9])
def test_mesh_volume_does_not_depend_on_where_the_mesh_lies(offset_mm):
    """An audit's affine 1e7 mm off the origin gave a simplified tumour a negative volume."""
    from tumor3d.simplify import simplify_mesh

    z, y, x = np.ogrid[:40, :40, :40]
    mask = (x - 19.5) ** 2 + (y - 19.5) ** 2 + (z - 19.5) ** 2 <= 15**2
    at_origin = simplify_mesh(extract_surface(mask, np.eye(4)), method="memoryless",
                              reduction_percent=60.0)  # fmt: skip
    far = Mesh(at_origin.vertices + offset_mm, at_origin.faces)
    # independent expectation: the same mesh's volume at the origin
    assert mesh_volume_mm3(far) == pytest.approx(mesh_volume_mm3(at_origin), rel=1e-9)
