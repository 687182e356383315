"""Exception types of tumor3d.

Every error a user can cause by passing bad input is an :class:`InputError`
(a :class:`ValueError`) whose message names the offending file, key or
parameter and says what is wrong with it.
"""

from __future__ import annotations


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
