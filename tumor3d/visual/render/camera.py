"""The views and the orthographic camera of :mod:`tumor3d.visual.render`.

The six anatomical views and the cut-away planes (name -> viewing
direction and image up, RAS), and :class:`Camera`, which maps RAS points to
pixel coordinates and names the image edges by their anatomical letters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: The six anatomical views: name -> (forward = viewing direction, image up), RAS.
_ANATOMICAL: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "anterior": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "posterior": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "right": ((-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "left": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "superior": ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
    "inferior": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
}


#: Cut-away planes: name -> the anatomical view that looks at the cut face.
_CUT_VIEW = {"axial": "superior", "coronal": "anterior", "sagittal": "right"}


ANATOMICAL_VIEWS: tuple[str, ...] = tuple(_ANATOMICAL)


CUTAWAYS: tuple[str, ...] = tuple(_CUT_VIEW)


# RAS axis letters: (+ letter, - letter) per axis.
_AXIS_LETTERS = (("R", "L"), ("A", "P"), ("S", "I"))


@dataclass(frozen=True)
class Camera:
    """An orthographic camera: RAS mm -> pixel coordinates.

    Parameters
    ----------
    centre : (3,) ndarray
        RAS point (mm) imaged at the image centre.
    forward, up : (3,) ndarray
        Unit viewing direction and image-up direction (orthogonal), RAS.
    pixels_per_mm : float
        Image scale, the same on both image axes.
    width, height : int
        Image size in pixels.
    """

    centre: np.ndarray
    forward: np.ndarray
    up: np.ndarray
    pixels_per_mm: float
    width: int
    height: int

    @property
    def right(self) -> np.ndarray:
        """Image-right direction in RAS, ``forward x up``."""
        return np.cross(self.forward, self.up)

    def project(self, points_ras: np.ndarray) -> np.ndarray:
        """Pixel coordinates of RAS points.

        Parameters
        ----------
        points_ras : (n, 3) array_like
            Points in RAS mm.

        Returns
        -------
        (n, 3) float64 ndarray
            ``(column, row, depth_mm)``: pixel ``(row, column)`` has its
            centre at integer coordinates, row 0 at the top; depth along
            ``forward`` from the centre (larger is farther from the camera).
        """
        p = np.asarray(points_ras, dtype=np.float64).reshape(-1, 3) - self.centre
        s = self.pixels_per_mm
        col = (self.width / 2.0) + (p @ self.right) * s - 0.5
        row = (self.height / 2.0) - (p @ self.up) * s - 0.5
        return np.stack([col, row, p @ self.forward], axis=1)

    def edge_labels(self) -> dict[str, str]:
        """Anatomical letters of the image edges (``left``, ``right``, ``top``, ``bottom``).

        The letter(s) of the RAS direction each edge points to; an oblique
        direction gets the letters of every axis with a component of at
        least ``sin 22.5 deg``, the dominant first (e.g. ``"LA"``).
        """
        r, u = self.right, self.up
        return {
            "left": _direction_letters(-r),
            "right": _direction_letters(r),
            "top": _direction_letters(u),
            "bottom": _direction_letters(-u),
        }


def _direction_letters(d: np.ndarray) -> str:
    d = np.asarray(d, dtype=np.float64)
    d = d / max(float(np.linalg.norm(d)), 1e-12)
    order = np.argsort(-np.abs(d), kind="stable")
    letters = [
        _AXIS_LETTERS[k][0 if d[k] > 0 else 1]
        for k in order
        if abs(d[k]) >= math.sin(math.radians(22.5))
    ]
    return "".join(letters)
