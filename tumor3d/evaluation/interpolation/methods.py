"""The methods compared, by the paper's names, and whether the ITK peer is installed."""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator

#: label -> keyword arguments of :func:`tumor3d.geometry.interpolate.interpolate_stack`.
METHODS: dict[str, dict[str, str]] = {
    "LG": {"method": "linear", "parts": "whole"},
    "SO": {"method": "shape", "parts": "whole"},
    "SE": {"method": "enhanced", "parts": "whole"},
    "SE-EDT": {"method": "enhanced-edt", "parts": "whole"},
    "SE parts": {"method": "enhanced", "parts": "matched"},
    "SE-EDT parts": {"method": "enhanced-edt", "parts": "matched"},
    "SO-EDT": {"method": "shape-edt", "parts": "whole"},
    "SO-EDT parts": {"method": "shape-edt", "parts": "matched"},
}
#: the label of ITK's MorphologicalContourInterpolator in the tables
ITK_METHOD = "ITK"
_ITK_HINT = (
    "ITK's MorphologicalContourInterpolator is an optional peer: "
    "pip install 'tumor3d[peers]' (itk-morphologicalcontourinterpolation)"
)


@contextlib.contextmanager
def _quiet_swig() -> Iterator[None]:
    """Silence SWIG's DeprecationWarnings while ITK loads and runs.

    ITK's SWIG wrappers warn ("builtin type SwigPyPacked has no __module__
    attribute") while its modules load lazily; with warnings turned into
    errors (``-W error``, pytest's ``filterwarnings = error``) the exception
    inside the module initialisation crashes the interpreter (segfault).
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        yield


def itk_available() -> bool:
    """True when ITK and its MorphologicalContourInterpolator module are installed.

    Checks the installed distributions without importing ITK (importing it
    is slow, and its teardown has crashed the interpreter at exit).
    """
    import importlib.metadata
    import importlib.util

    if importlib.util.find_spec("itk") is None:
        return False
    try:
        importlib.metadata.version("itk-morphologicalcontourinterpolation")
    except importlib.metadata.PackageNotFoundError:
        return False
    return True
