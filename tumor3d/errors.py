"""Exception types of tumor3d.

Every error a user can cause by passing bad input is an :class:`InputError`
(a :class:`ValueError`) whose message names the offending file, key or
parameter and says what is wrong with it.
"""

from __future__ import annotations

import errno
import os

__all__ = [
    "ConfigError",
    "InputError",
    "MeshError",
    "NoSurfaceError",
    "Tumor3DError",
    "exception_line",
    "os_error_line",
    "os_error_path",
    "os_error_text",
]


class Tumor3DError(Exception):
    """Base class of all tumor3d errors."""


class InputError(Tumor3DError, ValueError):
    """Bad user input: an unreadable file, an invalid value, an unsafe name.

    Parameters
    ----------
    message : str
        What is wrong, in words a user can act on.
    path : str, optional
        The file or folder concerned; it is prefixed to the message.
    """

    def __init__(self, message: str, path: str | None = None) -> None:
        self.path = None if path is None else str(path)
        self.problem = message
        super().__init__(f"{self.path}: {message}" if self.path else message)


class ConfigError(InputError):
    """An invalid configuration: unknown key or out-of-range value."""


class MeshError(Tumor3DError, ValueError):
    """A mesh that violates a requirement (shape, indices, manifoldness)."""


class NoSurfaceError(Tumor3DError, RuntimeError):
    """The mask holds no object, so there is no surface to extract."""


def exception_line(exc: BaseException, limit: int | None = None) -> str:
    r"""``Type: first line of the message`` (the type alone for an empty message).

    Cut to ``limit`` characters (ending in ``...``) when one is given.

    Examples
    --------
    >>> exception_line(ValueError("bad value\nmore detail"))
    'ValueError: bad value'
    >>> exception_line(KeyError())
    'KeyError'
    >>> exception_line(OSError("x" * 20), limit=12)
    'OSError: ...'
    >>> exception_line(OSError(28, "No space left on device", "out/p1/mesh.ply"))
    'OSError: out/p1/mesh.ply: no space left on device (ENOSPC)'
    """
    if isinstance(exc, OSError) and exc.errno is not None:  # the file and what, in words
        text = os_error_line(exc)
    else:
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    line = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    if limit is None or len(line) <= limit:
        return line
    return line[: limit - 3] + "..."


def os_error_text(exc: OSError) -> str:
    """One line describing an OS error for a user, without a traceback.

    Examples
    --------
    >>> os_error_text(OSError(28, "No space left on device"))
    'no space left on device (ENOSPC)'
    """
    text = (exc.strerror or str(exc) or type(exc).__name__).strip().splitlines()[0]
    code = errno.errorcode.get(exc.errno or -1)
    text = text[:1].lower() + text[1:]
    return f"{text} ({code})" if code else text


def os_error_line(exc: OSError) -> str:
    """``FILE: what happened (CODE)``, a rename's two files as ``A -> B``, for a user.

    Examples
    --------
    >>> os_error_line(OSError(28, "No space left on device", "out/p1/mesh.ply"))
    'out/p1/mesh.ply: no space left on device (ENOSPC)'
    >>> os_error_line(OSError(18, "Invalid cross-device link", "a", None, "b"))
    'a -> b: invalid cross-device link (EXDEV)'
    >>> os_error_line(OSError(28, "No space left on device"))
    'no space left on device (ENOSPC)'
    """
    where = str(exc.filename) if exc.filename else ""
    if exc.filename2:
        where = f"{where} -> {exc.filename2}"
    return f"{where}: {os_error_text(exc)}" if where else os_error_text(exc)


def os_error_path(exc: OSError, default: str | os.PathLike[str]) -> str:
    """The file an OS error concerns (its ``filename``), else ``default``."""
    return str(exc.filename) if exc.filename else os.fspath(default)
