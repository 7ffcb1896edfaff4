"""Typed errors.  All are ValueError subclasses so generic callers can catch ValueError."""

__all__ = ["InputError", "FileFormatError"]


class InputError(ValueError):
    """Bad user input (image, parameter, file); the message names the problem."""


class FileFormatError(InputError):
    """A data file is truncated, corrupt or not what its name says; the message names the file."""
