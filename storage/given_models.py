"""A user's trained models (``segment.learned_models: DIR``), read from their folder.

:func:`read_given_models` reads the model files of the folder ``tumor3d train --out DIR``
wrote (``hyper.npz``, ``t1c.npz``, ``unet_flair_seed<k>.npz``; anything else there,
``training.json`` say, is left unread), checks every one
(:func:`tumor3d.learned.bundle.check_models`: plain arrays, never unpickled) and returns
their bytes by file name. Every problem is one :class:`~tumor3d.errors.InputError` line
naming the folder or the file. The files are only read.
"""

from __future__ import annotations

import os
from pathlib import Path

from tumor3d.config import PipelineConfig
from tumor3d.errors import InputError
from tumor3d.learned.bundle import MAX_MODEL_BYTES, check_models, is_model_file

__all__ = ["read_given_models", "resolve_learned_models"]

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


def resolve_learned_models(cfg: PipelineConfig) -> PipelineConfig:
    """``cfg`` with ``segment.learned_models`` an absolute path, its folder checked.

    A command checks the folder before any flow runs (:func:`read_given_models`: one
    line) and hands on its absolute path, which means the same folder to a flow run
    in another working directory (a server, a scheduled run). Unset: ``cfg`` as it is.
    """
    where = cfg.segment.learned_models
    if where is None:
        return cfg
    read_given_models(where)
    folder = str(Path(where).expanduser().resolve())
    segment = cfg.segment.model_copy(update={"learned_models": folder})
    return cfg.model_copy(update={"segment": segment})
