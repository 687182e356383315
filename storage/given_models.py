"""A user's trained models (``segment.learned_models: DIR``), read from their folder.

:func:`read_given_models` reads the model files of the folder ``tumor3d train --out DIR``
wrote (``hyper.npz``, ``t1c.npz``, ``unet_flair_seed<k>.npz``; anything else there,
``training.json`` say, is left unread), checks every one
(:func:`tumor3d.learned.bundle.check_models`: plain arrays, never unpickled) and returns
their bytes by file name. Every problem is one :class:`~tumor3d.errors.InputError` line
naming the folder or the file. The files are only read. :func:`models_for` gives the
files one run uses (none where its method does not run the learned one), and
:func:`resolve_learned_models` checks a configuration's folder before any work.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from tumor3d.config import PipelineConfig, parse_config
from tumor3d.errors import ConfigError, InputError
from tumor3d.learned.bundle import (
    MAX_MODEL_BYTES,
    check_models,
    is_model_file,
    used_files,
    uses_models,
)

__all__ = ["models_for", "read_config_file", "read_given_models", "resolve_learned_models"]

_SETTING = "segment.learned_models"


def read_given_models(path: str | os.PathLike[str]) -> dict[str, bytes]:
    """The model files of the folder ``path`` (file name -> bytes), each checked.

    Raises
    ------
    InputError
        ``path`` is a URL, missing or not a folder, holds no forest model, or a
        model file is unreadable, too large or not a tumor3d model.
    """
    text = os.fspath(path)
    if "://" in text:
        raise InputError(f"{text}: {_SETTING} must be a local folder, not a URL")
    folder = Path(text).expanduser()
    if not folder.exists():
        raise InputError(f"{text}: no such folder ({_SETTING})")
    if not folder.is_dir():
        raise InputError(
            f"{text}: not a folder ({_SETTING} names the folder `tumor3d train --out` wrote)"
        )
    files: dict[str, bytes] = {}
    try:
        entries = sorted(e for e in folder.iterdir() if is_model_file(e.name))
        for entry in entries:
            if not entry.is_file():
                raise InputError(f"{entry}: not a file ({_SETTING})")
            size = entry.stat().st_size
            if size > MAX_MODEL_BYTES:
                raise InputError(
                    f"{entry}: {size / 2**20:.0f} MB, larger than any tumor3d model "
                    f"({MAX_MODEL_BYTES // 2**20} MB at most)"
                )
            files[entry.name] = entry.read_bytes()
    except OSError as exc:
        where = exc.filename or text
        raise InputError(f"{where}: cannot be read ({exc.strerror or exc})") from None
    check_models(files, source=text)
    return files


def models_for(cfg: PipelineConfig, modality: str) -> dict[str, bytes] | None:
    """The model files a run of ``modality`` with ``cfg`` uses, read and checked.

    None where ``segment.learned_models`` is unset or the method does not run the
    learned one on ``modality`` (``auto`` on T2, ``robust``, ...: the folder is not
    read); else the forest of the sequence's family and, on FLAIR with
    ``learned_cnn: auto``, the folder's U-Nets (:func:`tumor3d.learned.bundle.used_files`):
    what the segment stage's key and ``provenance.json`` then hold.

    Raises
    ------
    InputError
        :func:`read_given_models`' errors, or no forest for the sequence.
    """
    seg = cfg.segment
    if seg.learned_models is None or not uses_models(seg.method, modality):
        return None
    files = read_given_models(seg.learned_models)
    return used_files(files, modality, seg.learned_cnn, source=seg.learned_models)


def resolve_learned_models(
    cfg: PipelineConfig, modalities: Iterable[str] | None = None
) -> PipelineConfig:
    """``cfg`` with ``segment.learned_models`` an absolute path, checked for ``modalities``.

    The path made absolute means the same folder to a flow run in another working
    directory (a server, a scheduled run). With ``modalities`` (a run's, a manifest's),
    a command checks the folder before any work (one line): read where the method
    would use it on one of them, it must hold the forest of each (:func:`models_for`).
    Unset: ``cfg`` as it is.

    Raises
    ------
    InputError
        A URL, or :func:`models_for`' errors.
    """
    where = cfg.segment.learned_models
    if where is None:
        return cfg
    if "://" in where:
        raise InputError(f"{where}: {_SETTING} must be a local folder, not a URL")
    folder = str(Path(where).expanduser().resolve())
    segment = cfg.segment.model_copy(update={"learned_models": folder})
    cfg = cfg.model_copy(update={"segment": segment})
    for modality in sorted(set(modalities or ())):
        models_for(cfg, modality)
    return cfg


def read_config_file(path: str | os.PathLike[str]) -> PipelineConfig:
    """A YAML configuration file, validated, its ``segment.learned_models`` made absolute.

    The commands' and the scheduled runs' one reader (:func:`resolve_learned_models`;
    the folder is checked against the scans' sequences where those are known: the
    commands' ``_check_models``, each patient's run).

    Raises
    ------
    ConfigError
        An unreadable file, not UTF-8, or an invalid configuration (naming the file).
    InputError
        A models folder named by a URL.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read configuration: {exc.strerror}", path=str(path)) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start})",
            path=str(path),
        ) from None
    return resolve_learned_models(parse_config(text, source=str(path)))
