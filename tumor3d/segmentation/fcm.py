"""Fuzzy c-means on gray-level histograms (specification section 3, [A7]) and a naive reference.

The histogram form (:func:`fuzzy_cmeans_histogram`) costs ``O(G C I)`` for
``G`` gray levels, ``C`` clusters and ``I`` iterations, whatever the number
of pixels: bin ``g`` carries the weight ``h(g)`` of all pixels of gray level
``g``. :func:`fuzzy_cmeans_pixels` is Bezdek's per-pixel algorithm, ``O(N C
I)``, kept as the independent reference the histogram form is checked
against (both minimise the same objective, so they reach the same centres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tumor3d.errors import InputError

__all__ = [
    "FCMDiagnostics",
    "fcm_histogram",
    "fcm_memberships",
    "fuzzy_cmeans_histogram",
    "fuzzy_cmeans_pixels",
]

# --------------------------------------------------------------------------- fuzzy c-means


@dataclass(frozen=True)
class FCMDiagnostics:
    """Convergence record of :func:`fuzzy_cmeans_histogram`.

    Attributes
    ----------
    n_iter : int
        Number of centre updates performed.
    converged : bool
        Whether ``max |v_new - v_old| < tol`` was reached within ``max_num_iter``.
    objective : ndarray of float64, shape (n_iter,)
        ``J_m = sum_g h(g) sum_i u_i(g)^m (g - v_i)^2`` evaluated with the
        memberships and centres of each iteration (non-increasing).
    """

    n_iter: int
    converged: bool
    objective: np.ndarray


def fcm_memberships(gray: np.ndarray, centers: np.ndarray, fuzziness: float = 2.0) -> np.ndarray:
    r"""Fuzzy c-means memberships of gray levels to cluster centres.

    .. math::
        u_i(g) = \Big[\sum_c \big(|g - v_i| / |g - v_c|\big)^{2/(m-1)}\Big]^{-1},

    and ``u_i(g) = 1`` (0 for the others) when ``g = v_i`` (shared equally
    between coincident centres). Computed as ``r_i^p / sum_c r_c^p`` with
    ``r_i = min_c |g - v_c| / |g - v_i| <= 1``, which cannot overflow even for
    ``m`` close to 1.

    Parameters
    ----------
    gray : (G,) array_like of float
        Gray levels.
    centers : (C,) array_like of float
        Cluster centres ``v``.
    fuzziness : float
        The exponent ``m > 1``.

    Returns
    -------
    (C, G) ndarray of float64
        Memberships; every column sums to 1.
    """
    g = np.asarray(gray, dtype=np.float64).reshape(1, -1)
    v = np.asarray(centers, dtype=np.float64).reshape(-1, 1)
    p = 2.0 / (float(fuzziness) - 1.0)
    d = np.abs(g - v)
    dmin = d.min(axis=0, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(dmin > 0, dmin / d, (d == 0).astype(np.float64))
    w = ratio**p
    return w / w.sum(axis=0, keepdims=True)


def _fcm_histogram(
    hist: np.ndarray, centers: np.ndarray, m: float, tol: float, max_num_iter: int
) -> tuple[np.ndarray, FCMDiagnostics]:
    g = np.arange(hist.size, dtype=np.float64)
    v = centers.astype(np.float64).copy()
    objective = []
    converged = False
    n_iter = 0
    for n_iter in range(1, max_num_iter + 1):  # noqa: B007 (n_iter is reported)
        u = fcm_memberships(g, v, m)
        um_h = u**m * hist  # (C, G)
        denom = um_h.sum(axis=1)
        v_new = np.where(denom > 0, (um_h @ g) / np.where(denom > 0, denom, 1.0), v)
        u_new = fcm_memberships(g, v_new, m)
        objective.append(float(np.sum(hist * u_new**m * (g - v_new[:, None]) ** 2)))
        shift = float(np.max(np.abs(v_new - v)))
        v = v_new
        if shift < tol:
            converged = True
            break
    return v, FCMDiagnostics(n_iter=n_iter, converged=converged, objective=np.array(objective))


def fuzzy_cmeans_histogram(
    hist: np.ndarray,
    centers_init: np.ndarray,
    *,
    fuzziness: float = 2.0,
    tol: float = 1e-3,
    max_num_iter: int = 100,
    return_diagnostics: bool = False,
):
    r"""Fuzzy c-means on a gray-level histogram ([A7] step 2).

    Bin ``g`` of ``hist`` holds the number of pixels of gray level ``g``
    (``g = 0 .. G-1``), so one iteration costs ``O(G C)`` whatever the number
    of pixels. Alternating, from the initial centres ``v``:

    .. math::
        u_i(g) = \Big[\sum_c (|g - v_i| / |g - v_c|)^{2/(m-1)}\Big]^{-1},
        \qquad
        v_i = \frac{\sum_g h(g)\, u_i(g)^m\, g}{\sum_g h(g)\, u_i(g)^m},

    until ``max_i |dv_i| < tol`` or ``max_num_iter`` updates. This minimises
    the FCM objective ``J_m = sum_g h(g) sum_i u_i(g)^m (g - v_i)^2``, which
    equals the per-pixel objective of Bezdek's FCM on the pixels the
    histogram counts. A cluster whose weight ``sum_g h u^m`` vanishes keeps
    its centre.

    Parameters
    ----------
    hist : (G,) array_like of float
        Non-negative counts (weights) per gray level; not all zero.
    centers_init : (C,) array_like of float
        Initial centres (gray levels), e.g. the histogram peaks of section 2.
    fuzziness : float
        ``m > 1``; 2 in the paper's method.
    tol : float
        Convergence threshold on the largest centre change, gray levels.
    max_num_iter : int
        Maximum number of centre updates.
    return_diagnostics : bool
        Also return an :class:`FCMDiagnostics`.

    Returns
    -------
    centers : (C,) ndarray of float64
        Final centres, in the order of ``centers_init`` (not sorted).
    diagnostics : FCMDiagnostics
        Only if ``return_diagnostics``.

    Raises
    ------
    InputError
        If ``hist`` is not a non-negative finite 1-D array with positive
        sum, ``centers_init`` is empty or not finite, or a parameter is out
        of range.

    References
    ----------
    J. C. Bezdek, "Pattern Recognition with Fuzzy Objective Function
    Algorithms", Plenum, 1981. Arakeri & Reddy 2013, section 3.3 (FCM on the
    gray-level histogram, cost O(G C I)).

    Examples
    --------
    >>> h = np.zeros(256); h[[50, 52, 198, 200, 202]] = [10, 10, 5, 10, 5]
    >>> np.round(fuzzy_cmeans_histogram(h, [40.0, 210.0]), 1)
    array([ 51., 200.])
    """
    h = np.asarray(hist, dtype=np.float64)
    if h.ndim != 1 or h.size == 0:
        raise InputError(f"hist must be a non-empty 1-D array, got shape {h.shape}")
    if not np.all(np.isfinite(h)) or np.any(h < 0) or not h.sum() > 0:
        raise InputError("hist must be finite, non-negative and not all zero")
    v0 = np.asarray(centers_init, dtype=np.float64).reshape(-1)
    if v0.size == 0 or not np.all(np.isfinite(v0)):
        raise InputError("centers_init must hold at least one finite gray level")
    _check_fcm_params(fuzziness, tol, max_num_iter)
    v, diag = _fcm_histogram(h, v0, float(fuzziness), float(tol), int(max_num_iter))
    return (v, diag) if return_diagnostics else v


def _check_fcm_params(fuzziness: float, tol: float, max_num_iter: int) -> None:
    if not fuzziness > 1.0:
        raise InputError(f"fuzziness must be > 1, got {fuzziness}")
    if not tol > 0:
        raise InputError(f"tol must be > 0, got {tol}")
    if int(max_num_iter) < 1:
        raise InputError(f"max_num_iter must be >= 1, got {max_num_iter}")


def fcm_histogram(
    hist: np.ndarray, centers: np.ndarray, m: float, tol: float, max_num_iter: int
) -> tuple[np.ndarray, FCMDiagnostics]:
    """Unvalidated :func:`fuzzy_cmeans_histogram` for internal callers.

    Returns ``(centres, diagnostics)``.
    """
    h = np.asarray(hist, dtype=np.float64)
    return _fcm_histogram(h, np.asarray(centers), m, tol, max_num_iter)


def fuzzy_cmeans_pixels(
    values: np.ndarray,
    centers_init: np.ndarray,
    *,
    fuzziness: float = 2.0,
    tol: float = 1e-3,
    max_num_iter: int = 100,
) -> np.ndarray:
    r"""Bezdek's fuzzy c-means on individual pixel values (naive reference, ``O(N C I)``).

    .. math::
        u_{ij} = \Big[\sum_c (|x_j - v_i| / |x_j - v_c|)^{2/(m-1)}\Big]^{-1},
        \qquad v_i = \frac{\sum_j u_{ij}^m x_j}{\sum_j u_{ij}^m},

    iterated until ``max |dv| < tol``. Written as a plain loop over the pixels
    of every iteration's membership matrix, with no histogram, so that it is
    an independent check of :func:`fuzzy_cmeans_histogram`.

    Parameters
    ----------
    values : (N,) array_like of float
        Pixel values.
    centers_init : (C,) array_like of float
        Initial centres.
    fuzziness, tol, max_num_iter
        As in :func:`fuzzy_cmeans_histogram`.

    Returns
    -------
    (C,) ndarray of float64
        Final centres in the order of ``centers_init``.
    """
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    v = np.asarray(centers_init, dtype=np.float64).reshape(-1).copy()
    if x.size == 0 or v.size == 0:
        raise InputError("fuzzy_cmeans_pixels needs at least one value and one centre")
    _check_fcm_params(fuzziness, tol, max_num_iter)
    p = 2.0 / (float(fuzziness) - 1.0)
    for _ in range(int(max_num_iter)):
        num = np.zeros_like(v)
        den = np.zeros_like(v)
        for xj in x:
            d = np.abs(xj - v)
            if np.any(d == 0):
                u = (d == 0) / np.count_nonzero(d == 0)
            else:
                u = 1.0 / np.sum((d[:, None] / d[None, :]) ** p, axis=1)
            w = u ** float(fuzziness)
            num += w * xj
            den += w
        v_new = np.where(den > 0, num / np.where(den > 0, den, 1.0), v)
        shift = float(np.max(np.abs(v_new - v)))
        v = v_new
        if shift < tol:
            break
    return v
