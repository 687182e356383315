"""tumor3d: 3-D reconstruction and volume of brain tumours from thick-slice MR.

``tumor3d.reconstruct(image, modality=...)`` runs the whole method on one
patient in this process (no Prefect, no server; :mod:`tumor3d.api`) and
returns the masks, meshes, the volumes with Eq. 7's precision, the notes
and the status; ``tumor3d.__version__`` is the installed version.

The pure algorithmic core of the method of Arakeri & Reddy (2013),
"3D reconstruction of brain tumor and volume estimation from MR images",
IJSIP 6(3). Arrays in, arrays and dataclasses out: nothing in this package
imports Prefect or touches the file system.

Array conventions used throughout:

* image volumes are ``(z, y, x)``: ``z`` is the slice (acquisition) axis,
  ``y`` the row and ``x`` the column of a slice;
* affines are 4x4 and map the voxel index ``(x, y, z, 1)`` (note: the
  reverse of the array axis order, as NIfTI stores it) to RAS millimetres;
* meshes are ``(n, 3) float64`` vertices in RAS millimetres and
  ``(m, 3) int64`` faces, counter-clockwise seen from outside.
"""

from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _version

try:
    #: The installed package's version (pyproject.toml), as ``tumor3d --version`` says.
    __version__ = _version("tumor3d")
except PackageNotFoundError:  # pragma: no cover - a source tree that was never installed
    __version__ = "0+unknown"

__all__ = ["Reconstruction", "__version__", "reconstruct", "reconstruct_scan"]


def __getattr__(name: str):
    """``tumor3d.reconstruct`` and its result type, imported on first use (:mod:`tumor3d.api`).

    ``import tumor3d`` itself stays light: no scipy, numba or VTK until they are needed.
    """
    if name in ("Reconstruction", "reconstruct", "reconstruct_scan"):
        from tumor3d import api

        return getattr(api, name)
    raise AttributeError(f"module 'tumor3d' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The public names, the lazy ones included (tab completion in a notebook)."""
    return sorted({*globals(), *__all__})
