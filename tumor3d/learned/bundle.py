"""A user's trained models (``tumor3d train --out DIR``) in place of the shipped ones.

``segment.learned_models: DIR`` names a folder ``tumor3d train`` wrote: its forests
(``hyper.npz``: FLAIR and T2, ``t1c.npz``: T1c) and, with ``--cnn``, its FLAIR U-Nets
(``unet_flair_seed<k>.npz``). The caller reads the files
(:func:`tumor3d.storage.given_models.read_given_models`); here they are bytes:

* :func:`pack_models` / :func:`unpack_models`: the files as one ``.npz`` of byte
  arrays (read without pickle), the artifact whose content enters the segment
  stage's cache key;
* :func:`check_models`: every file parsed once, a bad one named in one line;
* :func:`uses_models` and :func:`used_files`: whether a run's segmentation may use
  them, and the files it may use (the forest of its sequence's family, and on FLAIR
  the U-Nets): only those are stored, key the segment stage and are recorded;
* :func:`model_set`: the models one sequence uses, with the files they came from
  (:class:`ModelSet`), as :func:`tumor3d.learned.shipped.shipped_models` gives the
  shipped ones.

The models of the folder, and only those: a FLAIR patient gets the folder's
U-Nets averaged with its forest when it holds some (``segment.learned_cnn: auto``),
its forest alone when it holds none; a sequence whose forest the folder lacks is an
error, never the shipped forest in its place.
"""

from __future__ import annotations

import io
import re
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from tumor3d.errors import InputError
from tumor3d.learned.archive import UNREADABLE, archive_error
from tumor3d.learned.cnn import UNetWeights, unet_from_bytes
from tumor3d.learned.forest import ForestModel

__all__ = [
    "FOREST_FILES",
    "MAX_MODEL_BYTES",
    "UNET_FILE",
    "ModelSet",
    "check_models",
    "is_model_file",
    "model_set",
    "pack_models",
    "unpack_models",
    "used_files",
    "uses_models",
]

#: The forest file of each family of sequences (:data:`tumor3d.learned.shipped.MODEL_FAMILIES`).
FOREST_FILES: dict[str, str] = {"hyper": "hyper.npz", "t1c": "t1c.npz"}

#: The FLAIR U-Nets' file names (one per training seed), as ``tumor3d train --cnn`` writes them.
UNET_FILE = re.compile(r"unet_flair_seed[0-9]{1,4}\.npz")

#: A model file larger than this is refused unread (the shipped ones are 0.1-0.5 MB).
MAX_MODEL_BYTES = 64 * 2**20


def is_model_file(name: str) -> bool:
    """Whether ``name`` is a model file a models folder may hold.

    >>> [is_model_file(n) for n in ("hyper.npz", "unet_flair_seed1.npz", "training.json")]
    [True, True, False]
    """
    return name in FOREST_FILES.values() or UNET_FILE.fullmatch(name) is not None


@dataclass(frozen=True)
class ModelSet:
    """The learned method's models for one sequence, and the files they came from.

    ``model`` the forest, ``cnn`` the U-Nets averaged with it (None: the forest
    alone), ``model_file`` and ``cnn_files`` where they were read from, as a run
    records them (``provenance.json``, the segment stage's values).
    """

    model: ForestModel
    cnn: tuple[UNetWeights, ...] | None
    model_file: str
    cnn_files: tuple[str, ...] = ()

    def keywords(self) -> dict[str, object]:
        """``model`` and ``cnn``: :func:`tumor3d.segmentation.segment.segment_tumor`'s keywords."""
        return {"model": self.model, "cnn": self.cnn}


def pack_models(files: Mapping[str, bytes]) -> bytes:
    """The model files as one ``.npz`` (file name -> its bytes as ``uint8``), sorted by name.

    The same files give the same bytes (no time stamps), so the same digest.

    >>> sorted(unpack_models(pack_models({"t1c.npz": b"ab", "hyper.npz": b"c"})).items())
    [('hyper.npz', b'c'), ('t1c.npz', b'ab')]
    """
    bad = [n for n in files if not is_model_file(n)]
    if bad:
        raise ValueError(f"not model file names: {bad}")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for name in sorted(files):
            arr = np.frombuffer(files[name], dtype=np.uint8)
            stem = name.removesuffix(".npz")
            entry = zipfile.ZipInfo(f"{stem}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            with zf.open(entry, "w") as fh:
                np.lib.format.write_array(fh, arr, allow_pickle=False)
    return buf.getvalue()


def unpack_models(data: bytes, *, source: str = "models") -> dict[str, bytes]:
    """:func:`pack_models`' files back (never unpickles); ``source`` names it in errors."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            files = {f"{k}.npz": np.asarray(z[k], dtype=np.uint8).tobytes() for k in z.files}
    except UNREADABLE as exc:
        why = archive_error(exc)
        raise InputError(f"{source}: not a packed set of tumor3d models ({why})") from None
    bad = [n for n in files if not is_model_file(n)]
    if bad:
        raise InputError(f"{source}: not a packed set of tumor3d models (holds {bad[0]})")
    return files


def _forest(files: Mapping[str, bytes], family: str, source: str) -> ForestModel:
    from tumor3d.learned.segment import check_model_features
    from tumor3d.learned.shipped import check_family

    name = FOREST_FILES[family]
    where = f"{source}/{name}"
    model = ForestModel.from_bytes(files[name], source=where)
    check_family(model, family, where)
    check_model_features(model, source=where)
    return model


def _unet_names(files: Mapping[str, bytes]) -> list[str]:
    """The U-Net files, by seed (``unet_flair_seed2`` before ``unet_flair_seed10``)."""
    names = [n for n in files if UNET_FILE.fullmatch(n)]
    return sorted(names, key=lambda n: int(n.removeprefix("unet_flair_seed").removesuffix(".npz")))


def check_models(files: Mapping[str, bytes], *, source: str) -> None:
    """Parse every model file once; one :class:`InputError` line naming a bad one.

    Raises
    ------
    InputError
        No forest in ``files``, a file that is not a model, a forest of the other
        family (a ``t1c.npz`` renamed ``hyper.npz``), or U-Nets of different inputs.
    """
    if not any(n in files for n in FOREST_FILES.values()):
        raise InputError(
            f"{source}: no learned model (hyper.npz for FLAIR and T2, t1c.npz for T1c, as "
            "`tumor3d train --out DIR` writes them)"
        )
    for family, name in FOREST_FILES.items():
        if name in files:
            _forest(files, family, source)
    nets = [unet_from_bytes(files[n], source=f"{source}/{n}") for n in _unet_names(files)]
    if len({(n.in_channels, n.size, n.framing) for n in nets}) > 1:
        raise InputError(
            f"{source}: its U-Nets see different inputs (context, size or framing): "
            "put the nets of one training together"
        )


def uses_models(method: str, modality: str) -> bool:
    """Whether ``segment.method`` may run the learned method on ``modality``.

    ``auto`` runs it on FLAIR and T1c, never on T2 (the paper's or the robust method);
    the rule-based methods never.

    >>> [uses_models(m, "t2") for m in ("auto", "learned", "robust")]
    [False, True, False]
    >>> uses_models("auto", "T1c")
    True
    """
    from tumor3d.segmentation.methods import method_spec
    from tumor3d.segmentation.segment import resolve_method

    return bool(method_spec(resolve_method(method, modality, None)).needs_model)


def used_files(
    files: Mapping[str, bytes], modality: str, learned_cnn: str = "auto", *, source: str
) -> dict[str, bytes]:
    """The files of a models folder that segment ``modality``: :func:`model_set`'s.

    Raises
    ------
    InputError
        The folder has no forest for the sequence (:func:`model_set`).
    """
    from tumor3d.learned.shipped import model_family

    name = FOREST_FILES[model_family(modality)]
    if name not in files:
        _no_forest(name, modality, source)
    nets = _unet_names(files) if _with_nets(modality, learned_cnn) else []
    return {n: files[n] for n in (name, *nets)}


def _with_nets(modality: str, learned_cnn: str) -> bool:
    """U-Nets beside the forest: ``learned_cnn`` auto, a sequence the shipped ones serve."""
    from tumor3d.learned.shipped import CNN_MODELS

    return learned_cnn == "auto" and modality.strip().lower() in CNN_MODELS


def _no_forest(name: str, modality: str, source: str) -> None:
    seqs = "FLAIR and T2" if name == FOREST_FILES["hyper"] else "T1c"
    raise InputError(
        f"{source}: no {name} ({seqs} model) for this {modality.strip().upper()} scan: train "
        f"one with {seqs} cases (`tumor3d train`), or leave segment.learned_models unset for "
        "the shipped models"
    )


def model_set(
    files: Mapping[str, bytes], modality: str, learned_cnn: str = "auto", *, source: str
) -> ModelSet:
    """The models of ``files`` (a models folder's) that segment ``modality``.

    The forest of the sequence's family; on FLAIR with ``learned_cnn`` ``"auto"``, the
    folder's U-Nets (all of them, by seed; none: the forest alone).

    Raises
    ------
    InputError
        The folder has no forest for the sequence (the shipped one is not put in its
        place), or a file is not a model (:func:`check_models`).
    """
    from tumor3d.learned.shipped import model_family

    family = model_family(modality)
    name, *nets = used_files(files, modality, learned_cnn, source=source)
    model = _forest(files, family, source)
    cnn = tuple(unet_from_bytes(files[n], source=f"{source}/{n}") for n in nets) or None
    return ModelSet(
        model=model,
        cnn=cnn,
        model_file=f"{source}/{name}",
        cnn_files=tuple(f"{source}/{n}" for n in nets),
    )
