"""Typed errors.  All are ValueError subclasses so generic callers can catch ValueError.

Messages that tell what to pass name the library's argument with the command's flag beside it
(``check_orientation=False (CLI: --no-orientation-check)``); while the ``femreg`` command runs
(:func:`cli_wording`) they name the flag alone (:func:`pass_as`), so a command-line user reads only flags."""
import contextlib

__all__ = ["InputError", "FileFormatError", "SpacingUnknownError", "cli_wording", "counted", "pass_as"]

# a process-wide switch, not a context variable: worker threads of the command word their messages alike
_cli = [False]


@contextlib.contextmanager
def cli_wording():
    """Within it, :func:`pass_as` gives the command's wording (``femreg.cli.main`` runs every subcommand so)."""
    before, _cli[0] = _cli[0], True
    try:
        yield
    finally:
        _cli[0] = before


def cli_wording_on() -> bool:
    """True within :func:`cli_wording` (a batch passes it on to its tasks, which run in other processes)."""
    return bool(_cli[0])


def pass_as(python: str, cli: str) -> str:
    """How a message names what to pass: ``cli`` (the command's flags only) within :func:`cli_wording`,
    ``python`` (the library's arguments, usually with the flag beside them) otherwise."""
    return cli if _cli[0] else python


def counted(n, noun: str, plural=None) -> str:
    """``n`` and ``noun`` in the number it takes: "1 node", "3 nodes" (``plural`` for an irregular one)."""
    return f"{n} {noun if int(n) == 1 else (plural or noun + 's')}"


class InputError(ValueError):
    """Bad user input (image, parameter, file); the message names the problem."""


class FileFormatError(InputError):
    """A data file is truncated, corrupt or not what its name says; the message names the file."""


class SpacingUnknownError(InputError):
    """A file without the pixel spacing it needs.  ``path`` the file, ``missing`` the axes without one ("axial
    dx", "lateral dy", ...), ``suggestion`` what its header fields imply
    (:class:`femreg.io.checks.SpacingSuggestion`) or None; ``frame_shape`` the (axial, lateral) samples of each
    frame as the file stores it (before a transpose), None where the reader does not say."""

    def __init__(self, message: str = "", *, path=None, missing=(), suggestion=None, frame_shape=None):
        super().__init__(message)
        self.path = path
        self.missing = tuple(missing)
        self.suggestion = suggestion
        self.frame_shape = None if frame_shape is None else tuple(int(v) for v in frame_shape)
