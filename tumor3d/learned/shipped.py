"""The learned segmentation models shipped inside the package, read without pickle.

The models are part of the code: read from the installed package's own
files (``importlib.resources``, as an import reads a module), never from a
user's path or an artifact store.

Each model is an ``.npz`` of plain arrays plus JSON metadata
(:meth:`tumor3d.learned.forest.ForestModel.from_bytes`, ``allow_pickle=False``)
in ``tumor3d/learned/models/``: ``hyper.npz`` (FLAIR and T2, whole tumour)
and ``t1c.npz`` (T1c, tumour core). Beside them, ``unet_flair_seed0.npz``
and ``unet_flair_seed1.npz``: two trainings (seeds 0 and 1) of a 2-D U-Net
(:mod:`tumor3d.learned.cnn`, weights only, read without pickle) on FLAIR
alone, each seeing 240 mm of each slice centred on the head (``framing: mm`` in
its settings, :func:`tumor3d.learned.cnn_data.frame_of`), an ensemble whose mean
probability the learned method averages with the forest's on FLAIR
(``segment.learned_cnn``). Their bytes enter the segment stage's cache key
(``tumor3d.tasks.caching.DATA_FILES``), so a retrained model recomputes.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cache
from importlib import resources
from typing import Any

from tumor3d.errors import InputError
from tumor3d.learned.bundle import ModelSet
from tumor3d.learned.cnn import UNetWeights, unet_from_bytes
from tumor3d.learned.forest import ForestModel

__all__ = [
    "CNN_MODELS",
    "MODEL_FAMILIES",
    "MODEL_IDENTITY_KEYS",
    "check_family",
    "model_family",
    "model_file",
    "model_identity",
    "shipped_cnn",
    "shipped_model",
    "shipped_models",
]

#: Which shipped model serves which sequence.
MODEL_FAMILIES: dict[str, str] = {"flair": "hyper", "t2": "hyper", "t1c": "t1c"}

#: Which sequences have a shipped U-Net (trained on FLAIR only): the stems of its
#: ensemble's files (the same network and data, trained with seeds 0 and 1; the
#: ensemble was chosen by cross-validation, ``reports/learned_cv.md``).
CNN_MODELS: dict[str, tuple[str, ...]] = {"flair": ("unet_flair_seed0", "unet_flair_seed1")}

#: The keys of :func:`model_identity` (the last two with the U-Net only), in its order.
MODEL_IDENTITY_KEYS = ("model", "model_file", "model_sha256", "cnn_model", "cnn_sha256")


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


def model_file(name: str) -> str:
    """Where a shipped model file ``name`` (``hyper``, ``unet_flair_seed0``, ...) is, as said.

    >>> model_file("hyper")
    'tumor3d/learned/models/hyper.npz'
    """
    return f"tumor3d/learned/models/{name}.npz"


@cache
def _load(family: str) -> ForestModel:
    where = model_file(family)
    ref = resources.files("tumor3d.learned").joinpath("models", f"{family}.npz")
    try:
        data = ref.read_bytes()
    except (FileNotFoundError, OSError) as exc:
        raise InputError(
            f"the learned model {family!r} is not installed ({where}): reinstall tumor3d or "
            "choose another segment.method"
        ) from exc
    model = ForestModel.from_bytes(data, source=where)
    check_family(model, family, where)
    return model


def check_family(model: ForestModel, family: str, where: str) -> None:
    """Refuse a model trained for another family of sequences than the file it sits in.

    ``tumor3d train`` records the family (``hyper``: FLAIR and T2, whole tumour; ``t1c``:
    tumour core) and its sequences in the model's metadata; a T1c model copied over
    ``hyper.npz`` would segment FLAIR's tumour core as if it were the whole tumour.
    A model without the record (none shipped) is taken as it is.

    Raises
    ------
    InputError
        Naming the file, the model's family and sequences and the expected family.
    """
    trained = model.meta.get("family")
    if trained is None or trained == family:
        return
    mods = ", ".join(str(m) for m in model.meta.get("modalities") or ()) or "?"
    wanted = ", ".join(m for m, f in MODEL_FAMILIES.items() if f == family)
    raise InputError(
        f"{where}: a model trained for {trained} ({mods}), not {family} ({wanted}): "
        f"put the {family} model there (`tumor3d train` writes {family}.npz)"
    )


def shipped_model(modality: str) -> ForestModel:
    """The shipped model for ``modality`` (read once per process)."""
    return _load(model_family(modality))


@cache
def _load_cnn(name: str) -> UNetWeights:
    where = model_file(name)
    ref = resources.files("tumor3d.learned").joinpath("models", f"{name}.npz")
    try:
        data = ref.read_bytes()
    except (FileNotFoundError, OSError) as exc:
        raise InputError(
            f"the U-Net {where} is not installed: reinstall tumor3d or set segment.learned_cnn: off"
        ) from exc
    return unet_from_bytes(data, source=where)


def shipped_cnn(modality: str) -> tuple[UNetWeights, ...] | None:
    """The shipped U-Net ensemble for ``modality`` (read once per process); None if none.

    >>> shipped_cnn("t2") is None
    True
    """
    names = CNN_MODELS.get(str(modality).strip().lower())
    return None if names is None else tuple(_load_cnn(n) for n in names)


def shipped_models(modality: str, learned_cnn: str = "auto") -> ModelSet:
    """The shipped models of the learned method for ``modality``, and their files.

    ``cnn`` is the shipped U-Net ensemble where ``learned_cnn`` is ``"auto"`` and one is
    shipped for the sequence (:data:`CNN_MODELS`), else None (the forest alone).
    One rule for the segment stage and :func:`tumor3d.api.reconstruct_scan`; a user's
    own models (``segment.learned_models``): :func:`tumor3d.learned.bundle.model_set`.
    """
    cnn = shipped_cnn(modality) if learned_cnn == "auto" else None
    names = CNN_MODELS[modality.strip().lower()] if cnn is not None else ()
    return ModelSet(
        model=shipped_model(modality),
        cnn=cnn,
        model_file=model_file(model_family(modality)),
        cnn_files=tuple(names),
    )


def model_identity(
    modality: str,
    model: ForestModel,
    cnn: UNetWeights | Sequence[UNetWeights] | None = None,
    *,
    files: ModelSet | None = None,
) -> dict[str, Any]:
    """The learned method's models as a run records them (stage values, ``provenance.json``).

    ``model`` (its name, ``"shipped"`` without one), ``model_file`` (the shipped file of
    the sequence's family, :func:`model_file`, or ``files.model_file``: a user's own
    models) and ``model_sha256`` (of that file, as ``training.json`` and ``sha256sum``
    give it; a model built in memory: of its arrays and metadata); with the U-Nets
    averaged with the forest (``cnn``), ``cnn_model`` (the shipped files' stems,
    :data:`CNN_MODELS`, or ``files.cnn_files``) and ``cnn_sha256`` (in that order; one
    net or an ensemble, as :func:`tumor3d.segmentation.segment.segment_tumor` takes them).
    """
    out: dict[str, Any] = {
        "model": model.meta.get("name", "shipped" if files is None else "unnamed"),
        "model_file": model_file(model_family(modality)) if files is None else files.model_file,
        "model_sha256": model.file_sha256 or model.digest(),
    }
    if cnn is not None:
        nets = (cnn,) if isinstance(cnn, UNetWeights) else tuple(cnn)
        names = list(CNN_MODELS[modality.lower()]) if files is None else list(files.cnn_files)
        out.update(
            cnn_model=names[: len(nets)],  # in cnn_sha256's order
            cnn_sha256=[n.sha256 for n in nets],
        )
    return out
