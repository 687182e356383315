"""The versions of the software a result depends on: one list, one function.

:func:`versions` is what ``provenance.json``, the publish key, the
evaluation report and the stages' cache keys read (issue 31: it existed
twice, with different package lists). :data:`NUMERICAL_PACKAGES` names the
packages whose code computes a stage's numbers: a stage's cache key holds
the versions of those its code closure imports
(:func:`tumor3d.tasks.caching.closure_packages`), so an upgrade that changes, say,
marching cubes recomputes the stages that call it.
"""

from __future__ import annotations

import platform
from functools import cache
from importlib import metadata as importlib_metadata

__all__ = [
    "NUMERICAL_DISTRIBUTIONS",
    "NUMERICAL_PACKAGES",
    "PACKAGES",
    "installed_version",
    "versions",
]

#: Import name -> the distributions whose versions decide what it computes. numba's
#: machine code comes from llvmlite's LLVM; ``open3d`` is installed as ``open3d-cpu``.
NUMERICAL_PACKAGES: dict[str, tuple[str, ...]] = {
    "numpy": ("numpy",),
    "scipy": ("scipy",),
    "skimage": ("scikit-image",),
    "numba": ("numba", "llvmlite"),
    "pywt": ("PyWavelets",),
    "fast_simplification": ("fast-simplification",),
    "open3d": ("open3d-cpu",),
    "nibabel": ("nibabel",),
    "pydicom": ("pydicom",),
    "SimpleITK": ("SimpleITK",),
    "PIL": ("pillow",),
    "pandas": ("pandas",),
}

#: The distributions of :data:`NUMERICAL_PACKAGES`, each once: those whose versions the
#: stages' cache keys may hold, and that every Dask worker must share.
NUMERICAL_DISTRIBUTIONS: tuple[str, ...] = tuple(
    dict.fromkeys(d for dists in NUMERICAL_PACKAGES.values() for d in dists)
)

#: Every distribution whose version is recorded: the numerical ones and the rest
#: of the software a result passes through (orchestration, validation, codecs, plots).
PACKAGES: tuple[str, ...] = (
    "prefect", "pydantic", "pyarrow", "isal", "vtk", "matplotlib", *NUMERICAL_DISTRIBUTIONS,
)  # fmt: skip


@cache
def installed_version(distribution: str) -> str:
    """The installed version of ``distribution`` (``not installed`` if absent); per process."""
    try:
        return importlib_metadata.version(distribution)
    except importlib_metadata.PackageNotFoundError:
        return "not installed"


@cache
def _platform() -> str:
    return platform.platform(terse=True)


def versions() -> dict[str, str]:
    """tumor3d, Python, the platform and every distribution of :data:`PACKAGES`.

    Looked up once per process (an upgrade takes effect in a new process,
    as the upgraded code does).
    """
    import tumor3d

    out = {
        "tumor3d": tumor3d.__version__,
        "python": platform.python_version(),
        "platform": _platform(),
    }
    out.update((name, installed_version(name)) for name in PACKAGES)
    return out
