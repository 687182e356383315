"""numba rasteriser of the phantom: inside tests, head fields, the supersampling renderer.

See :mod:`tumor3d.phantom` for the geometry and the packed vectors below.
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: Tissue label values of :attr:`PhantomPatient.tissue_labels`.
LABEL_NAMES: dict[int, str] = {
    0: "background",
    1: "scalp",
    2: "skull",
    3: "csf",
    4: "grey_matter",
    5: "white_matter",
    6: "tumour",
}
_BG, _SCALP, _SKULL, _CSF, _GM, _WM, _TUMOR = range(7)

#: Noise-free tissue intensities (arbitrary units, max ~1000), indexed by label.
TISSUE_INTENSITIES: dict[str, tuple[float, ...]] = {
    #        bg    scalp  skull  CSF    GM     WM     tumour
    "t2": (0.0, 600.0, 50.0, 950.0, 450.0, 300.0, 700.0),
    "flair": (0.0, 550.0, 50.0, 100.0, 450.0, 330.0, 850.0),
}


# Monomials q_x^i q_y^j q_z^k of degree 1..3 used by the wobble polynomials.
_MONOMIALS = np.array(
    [(i, j, k) for i in range(4) for j in range(4) for k in range(4) if 1 <= i + j + k <= 3],
    dtype=np.int64,
)
_WOBBLE_BALL = 1.2  # wobble is evaluated on q projected onto |q| <= 1.2
_BLOCK = 8  # pixel block size of the renderer's uniform-block test


# ---------------------------------------------------------------------------
# numba kernels
# ---------------------------------------------------------------------------
# Packed tumour vector (length 20):
#   [0] has_tumour, [1:4] t, [4:13] A^-1 (row-major), [13:16] s_x coefficients of
#   z, z^2, z^3, [16:19] s_y coefficients, [19] R0.
# Packed head vector (length 15):
#   [0:3] centre c, [3:6] semi-axes a, [6] thr_scalp_outer (=1), [7] thr_skull_outer,
#   [8] thr_brain_outer (on rho_h), [9] thr_csf_inner, [10] thr_gm_inner (on rho_b),
#   [11] Lipschitz of rho_h (1/mm), [12] Lipschitz of rho_b (1/mm),
#   [13] Hessian bound of w_h, [14] of w_h + w_b (both in q, on the ball |q| <= 1.2).


@numba.njit(cache=True, inline="always", fastmath=True)
def _tumor_inside(x, y, z, tum, dirs, amps, kappas):
    """Inside-test of one RAS point for the packed tumour (see module notes)."""
    if tum[0] == 0.0:
        return False
    vx = x - tum[1]
    vy = y - tum[2]
    vz = z - tum[3]
    sx = vz * (tum[13] + vz * (tum[14] + vz * tum[15]))
    sy = vz * (tum[16] + vz * (tum[17] + vz * tum[18]))
    vx -= sx
    vy -= sy
    wx = tum[4] * vx + tum[5] * vy + tum[6] * vz
    wy = tum[7] * vx + tum[8] * vy + tum[9] * vz
    wz = tum[10] * vx + tum[11] * vy + tum[12] * vz
    n = math.sqrt(wx * wx + wy * wy + wz * wz)
    if n == 0.0:
        return True
    s = 1.0
    for i in range(amps.shape[0]):
        cos_g = (wx * dirs[i, 0] + wy * dirs[i, 1] + wz * dirs[i, 2]) / n
        s += amps[i] * math.exp(kappas[i] * (cos_g - 1.0))
    return n <= tum[19] * s


@numba.njit(cache=True, fastmath=True)
def _contains_points(pts, tum, dirs, amps, kappas):
    out = np.zeros(pts.shape[0], dtype=np.bool_)
    for i in range(pts.shape[0]):
        out[i] = _tumor_inside(pts[i, 0], pts[i, 1], pts[i, 2], tum, dirs, amps, kappas)
    return out


@numba.njit(cache=True, inline="always", fastmath=True)
def _wobbles(qx, qy, qz, ch, cb):
    """Evaluate both wobble polynomials ``sum_m c[m] q^_MONOMIALS[m]``.

    ``q`` is first projected onto the ball ``|q| <= 1.2``. Unrolled for
    speed; the term order is that of ``_MONOMIALS``.
    """
    n = math.sqrt(qx * qx + qy * qy + qz * qz)
    if n > 1.2:
        f = 1.2 / n
        qx *= f
        qy *= f
        qz *= f
    m0 = qz
    m1 = qz * qz
    m2 = qz * qz * qz
    m3 = qy
    m4 = qy * qz
    m5 = qy * qz * qz
    m6 = qy * qy
    m7 = qy * qy * qz
    m8 = qy * qy * qy
    m9 = qx
    m10 = qx * qz
    m11 = qx * qz * qz
    m12 = qx * qy
    m13 = qx * qy * qz
    m14 = qx * qy * qy
    m15 = qx * qx
    m16 = qx * qx * qz
    m17 = qx * qx * qy
    m18 = qx * qx * qx
    wh = (
        ch[0] * m0
        + ch[1] * m1
        + ch[2] * m2
        + ch[3] * m3
        + ch[4] * m4
        + ch[5] * m5
        + ch[6] * m6
        + ch[7] * m7
        + ch[8] * m8
        + ch[9] * m9
        + ch[10] * m10
        + ch[11] * m11
        + ch[12] * m12
        + ch[13] * m13
        + ch[14] * m14
        + ch[15] * m15
        + ch[16] * m16
        + ch[17] * m17
        + ch[18] * m18
    )
    wb = (
        cb[0] * m0
        + cb[1] * m1
        + cb[2] * m2
        + cb[3] * m3
        + cb[4] * m4
        + cb[5] * m5
        + cb[6] * m6
        + cb[7] * m7
        + cb[8] * m8
        + cb[9] * m9
        + cb[10] * m10
        + cb[11] * m11
        + cb[12] * m12
        + cb[13] * m13
        + cb[14] * m14
        + cb[15] * m15
        + cb[16] * m16
        + cb[17] * m17
        + cb[18] * m18
    )
    return wh, wb


@numba.njit(cache=True, inline="always", fastmath=True)
def _head_fields(x, y, z, head, wob_h, wob_b):
    """Normalised head and brain radii ``(rho_h, rho_b)`` at one RAS point."""
    qx = (x - head[0]) / head[3]
    qy = (y - head[1]) / head[4]
    qz = (z - head[2]) / head[5]
    rq = math.sqrt(qx * qx + qy * qy + qz * qz)
    wh, wb = _wobbles(qx, qy, qz, wob_h, wob_b)
    return rq - wh, rq - wh - wb


@numba.njit(cache=True, inline="always", fastmath=True)
def _ventricle_rho(x, y, z, vent, i):
    qx = (x - vent[i, 0]) / vent[i, 3]
    qy = (y - vent[i, 1]) / vent[i, 4]
    qz = (z - vent[i, 2]) / vent[i, 5]
    return math.sqrt(qx * qx + qy * qy + qz * qz)


@numba.njit(cache=True, inline="always", fastmath=True)
def _head_label(x, y, z, rho_h, rho_b, head, vent):
    """Tissue label (0-5) of the head at one RAS point from its fields."""
    if rho_h >= head[6]:
        return _BG
    if rho_h >= head[7]:
        return _SCALP
    if rho_h >= head[8]:
        return _SKULL
    if rho_b >= head[9]:
        return _CSF
    for i in range(vent.shape[0]):
        if _ventricle_rho(x, y, z, vent, i) < 1.0:
            return _CSF
    if rho_b >= head[10]:
        return _GM
    return _WM


@numba.njit(cache=True, inline="always", fastmath=True)
def _box_overlaps(x, y, z, half, bbox):
    """Whether the box ``[x +- half[0]] x [y +- half[1]] x [z +- half[2]]`` meets ``bbox``."""
    return (
        x + half[0] >= bbox[0]
        and x - half[0] <= bbox[3]
        and y + half[1] >= bbox[1]
        and y - half[1] <= bbox[4]
        and z + half[2] >= bbox[2]
        and z - half[2] <= bbox[5]
    )


@numba.njit(cache=True, inline="always", fastmath=True)
def _label_at(x, y, z, head, wob_h, wob_b, vent, tum, dirs, amps, kappas, tum_bbox, zero3):
    """Tissue label (0-6) at one RAS point; the tumour overrides the head."""
    if (
        tum[0] != 0.0
        and _box_overlaps(x, y, z, zero3, tum_bbox)
        and _tumor_inside(x, y, z, tum, dirs, amps, kappas)
    ):
        return _TUMOR
    rho_h, rho_b = _head_fields(x, y, z, head, wob_h, wob_b)
    return _head_label(x, y, z, rho_h, rho_b, head, vent)


@numba.njit(cache=True, inline="always", fastmath=True)
def _wobble_gradients(qx, qy, qz, ch, cb):
    """Gradients in ``q`` of both wobble polynomials, unprojected (``|q| <= 1.2``).

    The partial derivatives of :func:`_wobbles`' monomials ``m0 .. m18``, term by term.
    """
    xx = qx * qx
    yy = qy * qy
    zz = qz * qz
    xy = qx * qy
    xz = qx * qz
    yz = qy * qz
    out = np.empty(6)
    for t in range(2):
        c = ch if t == 0 else cb
        out[3 * t] = (
            c[9] + c[10] * qz + c[11] * zz + c[12] * qy + c[13] * yz + c[14] * yy
            + 2.0 * (c[15] * qx + c[16] * xz + c[17] * xy) + 3.0 * c[18] * xx
        )  # fmt: skip
        out[3 * t + 1] = (
            c[3] + c[4] * qz + c[5] * zz + 2.0 * (c[6] * qy + c[7] * yz) + 3.0 * c[8] * yy
            + c[12] * qx + c[13] * xz + 2.0 * c[14] * xy + c[17] * xx
        )  # fmt: skip
        out[3 * t + 2] = (
            c[0] + 2.0 * c[1] * qz + 3.0 * c[2] * zz + c[4] * qy + 2.0 * c[5] * yz + c[7] * yy
            + c[10] * qx + 2.0 * c[11] * xz + c[13] * xy + c[16] * xx
        )  # fmt: skip
    return out


# Not inlined: it runs only where the Lipschitz test fails, and inlined into the renderer's
# two purity tests it made the first phantom of an empty numba cache compile 10.5 s, not 8.4.
@numba.njit(cache=True, fastmath=True)
def _fields_pure_near(x, y, z, rho_h, rho_b, box, head, wob_h, wob_b):
    """Second-order test that no head threshold crosses the box around ``(x, y, z)``.

    For ``f = |q| - w(q)`` and ``|dq_r| <= beta_r = box_r / a_r`` over the box:
    ``|f(q0 + dq) - f(q0)| <= sum_r |df/dq_r(q0)| beta_r + |beta|^2 (1 / q_min + H_w) / 2``,
    where ``1 / q_min`` bounds the Hessian of ``|q|`` on the annulus the box maps into and
    ``H_w`` (``head[13]``, ``head[14]``) that of the wobbles on the ball ``|q| <= 1.2``,
    inside which no projection acts. The box need only clear each threshold by this
    margin; the Lipschitz test asks for the gradient's worst direction and length, which
    the slab's depth makes ~4x wider at a boundary that runs through the slice.
    """
    qx = (x - head[0]) / head[3]
    qy = (y - head[1]) / head[4]
    qz = (z - head[2]) / head[5]
    n = math.sqrt(qx * qx + qy * qy + qz * qz)
    bx = box[0] / head[3]
    by = box[1] / head[4]
    bz = box[2] / head[5]
    beta2 = bx * bx + by * by + bz * bz
    beta = math.sqrt(beta2)
    q_min = n - beta
    if q_min <= 0.05 or n + beta > _WOBBLE_BALL:
        return False
    g = _wobble_gradients(qx, qy, qz, wob_h, wob_b)
    ux = qx / n - g[0]
    uy = qy / n - g[1]
    uz = qz / n - g[2]
    curv = 0.5 * beta2 * (1.0 / q_min + head[13])
    mh = abs(ux) * bx + abs(uy) * by + abs(uz) * bz + curv + 1e-9
    for k in range(6, 9):
        if abs(rho_h - head[k]) <= mh:
            return False
    ux -= g[3]
    uy -= g[4]
    uz -= g[5]
    curv = 0.5 * beta2 * (1.0 / q_min + head[14])
    mb = abs(ux) * bx + abs(uy) * by + abs(uz) * bz + curv + 1e-9
    for k in range(9, 11):
        if abs(rho_b - head[k]) <= mb:
            return False
    return True


@numba.njit(cache=True, inline="always", fastmath=True)
def _is_pure(x, y, z, rho_h, rho_b, half_diag, box, head, wob_h, wob_b, vent, tum_bbox):
    """Tell whether one label fills the whole sample box around ``(x, y, z)``.

    No boundary can cross the ball of radius ``half_diag`` (which holds the
    box) when every field is farther from its thresholds than its Lipschitz
    bound times ``half_diag`` (``head[11]`` for ``rho_h``, ``head[12]`` for
    ``rho_b``, ``1 / min(semi-axes)`` for a ventricle's radius); where that
    first test fails near a head threshold, :func:`_fields_pure_near` bounds the
    fields over the box itself. Any overlap of the box with the tumour's
    bounding box makes the pixel impure.
    """
    if tum_bbox[0] <= tum_bbox[3] and _box_overlaps(x, y, z, box, tum_bbox):
        return False
    near = False
    mh = head[11] * half_diag
    for k in range(6, 9):
        if abs(rho_h - head[k]) <= mh:
            near = True
    mb = head[12] * half_diag
    for k in range(9, 11):
        if abs(rho_b - head[k]) <= mb:
            near = True
    if near and not _fields_pure_near(x, y, z, rho_h, rho_b, box, head, wob_h, wob_b):
        return False
    for i in range(vent.shape[0]):
        amin = min(vent[i, 3], min(vent[i, 4], vent[i, 5]))
        if abs(_ventricle_rho(x, y, z, vent, i) - 1.0) <= half_diag / amin:
            return False
    return True


@numba.njit(cache=True, fastmath=True)
def _render(
    aff,
    nz,
    ny,
    nx,
    sub_xy,
    sub_z,
    head,
    wob_h,
    wob_b,
    vent,
    tum,
    dirs,
    amps,
    kappas,
    tum_bbox,
    values,
    adaptive,
):
    """Partial-volume image and centre labels of every slice.

    ``sub_xy`` are in-plane sub-sample offsets (pixel units), ``sub_z`` the
    through-slice offsets (slice-index units); a pixel's value is the mean
    of ``values[label]`` over the ``len(sub_xy)**2 * len(sub_z)`` samples.
    With ``adaptive``, blocks of ``_BLOCK x _BLOCK`` pixels, and then single
    pixels, that :func:`_is_pure` proves uniform get ``values[label]`` at
    once. ``tum_bbox`` (min3, max3) must hold the
    tumour; give ``min > max`` when there is none. Returns
    ``(image float64, labels uint8)``, both ``(nz, ny, nx)``.
    """
    image = np.empty((nz, ny, nx), dtype=np.float64)
    labels = np.empty((nz, ny, nx), dtype=np.uint8)
    zero3 = np.zeros(3)
    mxy = np.max(np.abs(sub_xy))
    mz = np.max(np.abs(sub_z))
    # half extents (mm) of one pixel's sample box and its half diagonal
    box = np.zeros(3)
    for r in range(3):
        box[r] = (abs(aff[r, 0]) + abs(aff[r, 1])) * mxy + abs(aff[r, 2]) * mz
    half_diag = math.sqrt(box[0] ** 2 + box[1] ** 2 + box[2] ** 2)
    bbox = np.zeros(3)
    for k in range(nz):
        for j0 in range(0, ny, _BLOCK):
            j1 = min(j0 + _BLOCK, ny)
            for i0 in range(0, nx, _BLOCK):
                i1 = min(i0 + _BLOCK, nx)
                if adaptive:
                    # whole block uniform? (covers all its pixels' sample boxes)
                    ic = 0.5 * (i0 + i1 - 1)
                    jc = 0.5 * (j0 + j1 - 1)
                    x = aff[0, 0] * ic + aff[0, 1] * jc + aff[0, 2] * k + aff[0, 3]
                    y = aff[1, 0] * ic + aff[1, 1] * jc + aff[1, 2] * k + aff[1, 3]
                    z = aff[2, 0] * ic + aff[2, 1] * jc + aff[2, 2] * k + aff[2, 3]
                    for r in range(3):
                        bbox[r] = (
                            abs(aff[r, 0]) * (0.5 * (i1 - i0 - 1) + mxy)
                            + abs(aff[r, 1]) * (0.5 * (j1 - j0 - 1) + mxy)
                            + abs(aff[r, 2]) * mz
                        )
                    hd = math.sqrt(bbox[0] ** 2 + bbox[1] ** 2 + bbox[2] ** 2)
                    rho_h, rho_b = _head_fields(x, y, z, head, wob_h, wob_b)
                    if _is_pure(
                        x, y, z, rho_h, rho_b, hd, bbox, head, wob_h, wob_b, vent, tum_bbox
                    ):
                        lab = _head_label(x, y, z, rho_h, rho_b, head, vent)
                        for j in range(j0, j1):
                            for i in range(i0, i1):
                                labels[k, j, i] = lab
                                image[k, j, i] = values[lab]
                        continue
                for j in range(j0, j1):
                    for i in range(i0, i1):
                        lab, val = _render_pixel(
                            aff,
                            k,
                            j,
                            i,
                            sub_xy,
                            sub_z,
                            head,
                            wob_h,
                            wob_b,
                            vent,
                            tum,
                            dirs,
                            amps,
                            kappas,
                            tum_bbox,
                            values,
                            adaptive,
                            half_diag,
                            box,
                            zero3,
                        )
                        labels[k, j, i] = lab
                        image[k, j, i] = val
    return image, labels


@numba.njit(cache=True, inline="always", fastmath=True)
def _render_pixel(
    aff,
    k,
    j,
    i,
    sub_xy,
    sub_z,
    head,
    wob_h,
    wob_b,
    vent,
    tum,
    dirs,
    amps,
    kappas,
    tum_bbox,
    values,
    adaptive,
    half_diag,
    box,
    zero3,
):
    """Centre label and partial-volume value of pixel ``(k, j, i)``."""
    x = aff[0, 0] * i + aff[0, 1] * j + aff[0, 2] * k + aff[0, 3]
    y = aff[1, 0] * i + aff[1, 1] * j + aff[1, 2] * k + aff[1, 3]
    z = aff[2, 0] * i + aff[2, 1] * j + aff[2, 2] * k + aff[2, 3]
    rho_h, rho_b = _head_fields(x, y, z, head, wob_h, wob_b)
    if (
        tum[0] != 0.0
        and _box_overlaps(x, y, z, zero3, tum_bbox)
        and _tumor_inside(x, y, z, tum, dirs, amps, kappas)
    ):
        lab = _TUMOR
    else:
        lab = _head_label(x, y, z, rho_h, rho_b, head, vent)
    if adaptive and _is_pure(
        x, y, z, rho_h, rho_b, half_diag, box, head, wob_h, wob_b, vent, tum_bbox
    ):
        return lab, values[lab]
    acc = 0.0
    for a in range(sub_z.shape[0]):
        kk = k + sub_z[a]
        for b in range(sub_xy.shape[0]):
            jj = j + sub_xy[b]
            for c in range(sub_xy.shape[0]):
                ii = i + sub_xy[c]
                xs = aff[0, 0] * ii + aff[0, 1] * jj + aff[0, 2] * kk + aff[0, 3]
                ys = aff[1, 0] * ii + aff[1, 1] * jj + aff[1, 2] * kk + aff[1, 3]
                zs = aff[2, 0] * ii + aff[2, 1] * jj + aff[2, 2] * kk + aff[2, 3]
                acc += values[
                    _label_at(
                        xs,
                        ys,
                        zs,
                        head,
                        wob_h,
                        wob_b,
                        vent,
                        tum,
                        dirs,
                        amps,
                        kappas,
                        tum_bbox,
                        zero3,
                    )
                ]
    return lab, acc / (sub_xy.shape[0] * sub_xy.shape[0] * sub_z.shape[0])


@numba.njit(cache=True, fastmath=True)
def _mask_in_box(aff, lo, hi, tum, dirs, amps, kappas, out):
    """Fill ``out[k, j, i]`` with the tumour inside-test for indices in ``[lo, hi)``."""
    for k in range(lo[0], hi[0]):
        for j in range(lo[1], hi[1]):
            for i in range(lo[2], hi[2]):
                x = aff[0, 0] * i + aff[0, 1] * j + aff[0, 2] * k + aff[0, 3]
                y = aff[1, 0] * i + aff[1, 1] * j + aff[1, 2] * k + aff[1, 3]
                z = aff[2, 0] * i + aff[2, 1] * j + aff[2, 2] * k + aff[2, 3]
                out[k, j, i] = _tumor_inside(x, y, z, tum, dirs, amps, kappas)


@numba.njit(cache=True, fastmath=True)
def _head_fields_many(pts, head, wob_h, wob_b):
    """``(rho_h, rho_b)`` at each row of ``pts`` (RAS mm), shape ``(n, 2)``."""
    out = np.empty((pts.shape[0], 2))
    for i in range(pts.shape[0]):
        rho_h, rho_b = _head_fields(pts[i, 0], pts[i, 1], pts[i, 2], head, wob_h, wob_b)
        out[i, 0] = rho_h
        out[i, 1] = rho_b
    return out
