"""The learned segmentation models shipped inside the package, read without pickle.

The models are part of the code: read from the installed package's own
files (``importlib.resources``, as an import reads a module), never from a
user's path or an artifact store.

Each model is an ``.npz`` of plain arrays plus JSON metadata
(:meth:`tumor3d.learned.forest.ForestModel.from_bytes`, ``allow_pickle=False``)
in ``tumor3d/learned/models/``: ``hyper.npz`` (FLAIR and T2, whole tumour)
and ``t1c.npz`` (T1c, tumour core). Their bytes enter the segment stage's
cache key (``tumor3d.tasks.caching.DATA_FILES``), so a retrained model recomputes.
"""

from __future__ import annotations

from functools import cache
from importlib import resources

from tumor3d.errors import InputError
from tumor3d.learned.forest import ForestModel

__all__ = ["MODEL_FAMILIES", "model_family", "shipped_model"]

#: Which shipped model serves which sequence.
MODEL_FAMILIES: dict[str, str] = {"flair": "hyper", "t2": "hyper", "t1c": "t1c"}


def model_family(modality: str) -> str:
    """``"hyper"`` for FLAIR and T2, ``"t1c"`` for T1c.

    >>> model_family("T2")
    'hyper'
    """
    mod = str(modality).strip().lower()
    if mod not in MODEL_FAMILIES:
        raise InputError(
            f"no learned model for modality {modality!r}: expected one of {sorted(MODEL_FAMILIES)}"
        )
    return MODEL_FAMILIES[mod]


@cache
def _load(family: str) -> ForestModel:
    ref = resources.files("tumor3d.learned").joinpath("models", f"{family}.npz")
    try:
        data = ref.read_bytes()
    except (FileNotFoundError, OSError) as exc:
        raise InputError(
            f"the learned model {family!r} is not installed (tumor3d/learned/models/"
            f"{family}.npz): reinstall tumor3d or choose another segment.method"
        ) from exc
    return ForestModel.from_bytes(data)


def shipped_model(modality: str) -> ForestModel:
    """The shipped model for ``modality`` (read once per process)."""
    return _load(model_family(modality))
