"""Typed errors.  All are ValueError subclasses so generic callers can catch ValueError."""

__all__ = ["InputError", "FileFormatError", "SpacingUnknownError"]


class InputError(ValueError):
    """Bad user input (image, parameter, file); the message names the problem."""


class FileFormatError(InputError):
    """A data file is truncated, corrupt or not what its name says; the message names the file."""


class SpacingUnknownError(InputError):
    """A file without the pixel spacing it needs.  ``path`` the file, ``missing`` the axes without one ("axial
    dx", "lateral dy", ...), ``suggestion`` what its header fields imply
    (:class:`femreg.io.checks.SpacingSuggestion`) or None."""

    def __init__(self, message: str = "", *, path=None, missing=(), suggestion=None):
        super().__init__(message)
        self.path = path
        self.missing = tuple(missing)
        self.suggestion = suggestion
