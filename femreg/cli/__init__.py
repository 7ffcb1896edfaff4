"""The ``femreg`` command.  Each subcommand lives in its own module of this package exposing
``add_parser(subparsers)`` (which calls ``parser.set_defaults(func=run)``) and ``run(args) -> int``;
modules named ``*_cmd`` are found automatically.  Other packages add subcommands through the ``femreg.commands``
entry-point group (``NAME = "package.module:add_parser"`` in their pyproject.toml; the object is an
``add_parser(subparsers)`` as above); ``forward`` contributes ``simulate`` and ``forward``, ``paperstudy`` contributes
``study``.  A contributed subcommand is imported only when it is run or when the help lists all commands, so
femreg itself never imports those packages.

Bad input -> one line ``femreg <cmd>: error: <reason>`` on stderr and exit code 2 (raise
:class:`femreg.errors.InputError` or ``ValueError`` from a subcommand; both are caught here).  A computation that
fails (exit code 1) reads ``femreg <cmd>: failed: <reason>`` (or ``FAILED:`` / ``FLAGGED:`` for a result written
and marked so), never ``error:``, so a log tells the two apart.  A missing optional package
(:class:`femreg.optional.MissingDependencyError`) -> one line ``failed:`` naming the extra to install, exit code 1.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from ..progress import stderr_is_terminal

#: Subcommand modules are discovered (every ``*_cmd`` module of this package); this fixes the --help order.
ORDER = ["register_cmd", "track_cmd", "elastogram_cmd", "info_cmd", "plot_cmd", "measure_cmd"]
#: Entry-point group through which other packages contribute subcommands.
ENTRY_POINT_GROUP = "femreg.commands"

#: What exit codes 0 and 1 mean for each of femreg's own subcommands, and examples of the bad input of code 2
#: (for all: found before any work, one line on stderr); shown at the end of every subcommand's --help, as the
#: README's table says.
EXIT_CODES = {
    "register": ("registered", "registered, but the registration failed its check or its NCC after is below "
                               "--min-ncc (the result is written, the reason printed)"),
    "track": ("every frame registered", "a frame flagged (failed its check, low NCC) or not computed: finished "
                                        "frames are kept, --resume continues"),
    "elastogram": ("done", "nothing usable: no pair in the band registered (the screening is written)"),
    "info": ("described, ready to register", "described, but something is needed first (no spacing, a transposed "
                                             "frame: printed)",
             "the file cannot be read: a raw file without --shape, the wrong --dtype, no such variable, a corrupt "
             "file, a femreg result"),
    "plot": ("drawn", "drawn, but the result is a failed or flagged registration or inversion (printed)",
             "not a result file, bad flags"),
    "measure": ("measured", "measured, but the result is a failed one (the numbers marked FLAGGED)",
                "not a result file, a region outside the mesh (its bounds printed), bad flags"),
    "batch": ("every task done, none flagged", "a task failed or was flagged (the summary names it; --resume "
                                               "reruns the failed ones)"),
    "invert": ("inverted", "inverted, but the optimisation failed or the result is flagged, or --allow-failed on a "
                           "failed registration (the result is written, the reason printed)",
               "not a result file, a failed registration without --allow-failed, a --region outside the mesh, bad "
               "flags"),
}


def exit_code_epilog(name: str) -> str:
    """The --help epilog stating ``name``'s exit codes (:data:`EXIT_CODES`)."""
    done, flagged, *bad = EXIT_CODES[name]
    bad = bad[0] if bad else ("unreadable file, bad flags, frames that look transposed (--transpose reads frames "
                              "stored lines first), a swapped spacing, ...")
    return (f"exit codes: 0 {done}; 1 {flagged}, said on stderr as 'failed:', 'FAILED:' or 'FLAGGED:'; 2 bad "
            f"input, found before any work, with a one-line 'error:' reason on stderr ({bad}).")


def _command_modules() -> list[str]:
    import pkgutil

    found = {m.name for m in pkgutil.iter_modules(__path__) if m.name.endswith("_cmd")}
    return [n for n in ORDER if n in found] + sorted(found - set(ORDER))


def _contributed() -> dict:
    """{subcommand name: entry point} of the ``femreg.commands`` group (nothing is imported here)."""
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name)}


#: What argparse's "expected N arguments" error of an option leaves out: the values it takes.
_NARGS_HINTS = {
    "--spacing": "give the axial and the lateral spacing in mm (--spacing DX DY), for volumes the elevational plane "
                 "spacing too (--spacing DX DY DZ); 'auto' keeps the file's value for one of them (convex / sector "
                 "frames: --spacing DR auto, the range step with the angle from the geometry)",
    "--origin": "give the depth of the first sample and the lateral position of the first line in mm "
                "(--origin X0 Y0)",
}


class _Parser(argparse.ArgumentParser):
    """argparse's parser whose errors of an option given too few values say which values it takes, and whose
    ``--spacing`` (two or three values) leaves the files written after its values to the command
    (:func:`femreg.cli._common.spacing_values_first`)."""

    def parse_known_args(self, args=None, namespace=None):
        if args is not None and "--spacing" in self._option_string_actions:
            from ._common import spacing_values_first

            args = spacing_values_first(args)
        return super().parse_known_args(args, namespace)

    def _get_formatter(self):
        formatter = super()._get_formatter()
        plain = formatter._format_args
        # an option taking a set of counts (--spacing DX DY [DZ]) shows them, not argparse's "X [X ...]"
        formatter._format_args = lambda action, default: getattr(action, "usage_metavar", None) or plain(action,
                                                                                                         default)
        return formatter

    def error(self, message):
        for opt, hint in _NARGS_HINTS.items():
            if message.startswith(f"argument {opt}: expected"):
                message = f"{message}: {hint}"
        super().error(message)


def build_parser(argv=None) -> argparse.ArgumentParser:
    """The parser; when ``argv`` names a contributed subcommand only that one is imported, otherwise all are (the
    help lists them)."""
    parser = _Parser(
        prog="femreg",
        description="Finite-element ultrasound elastography with momentum (SPREME) regularisation.",
        epilog="The first run on a machine compiles the numerical kernels (numba, about 9-14 s, said once on a "
               "terminal); later runs load them from the cache.  FEMREG_NUMBA=0 runs without them.")
    from femreg import __version__
    parser.add_argument("--version", action="version", version=f"femreg {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _command_modules():
        importlib.import_module(f"femreg.cli.{name}").add_parser(sub)
    for name, sp in sub.choices.items():
        if name in EXIT_CODES and not sp.epilog:
            sp.epilog = exit_code_epilog(name)
        if name in EXIT_CODES and "--no-progress" not in sp._option_string_actions:
            # a script passing it to every command must not fail on the ones that show no bar
            sp.add_argument("--no-progress", action="store_true",
                            help="accepted by every command; this one shows no progress bar")
    plugins = _contributed()
    first = next((a for a in (argv or []) if not a.startswith("-")), None)
    wanted = [first] if first in plugins else ([] if first in sub.choices else sorted(plugins))
    for name in wanted:
        try:
            add = plugins[name].load()
        except ImportError as exc:  # a contributing package that is broken must not take the other commands down
            print(f"femreg: subcommand {name!r} unavailable ({exc})", file=sys.stderr)
            continue
        add(sub)
    return parser


def _name_the_files(args, exc, msg: str) -> str:
    """``msg`` of a frame check that ran on the frames, not the file (transposed, swapped spacing), led by the
    input file(s) it judged, as the checks on the file as read are."""
    from femreg.orientation import OrientationError

    if not isinstance(exc, OrientationError):
        return msg
    files = [str(v) for v in (getattr(args, k, None) for k in ("reference", "moving", "file")) if v is not None]
    if not files or any(msg.startswith(f) for f in files):
        return msg
    return f"{', '.join(files)}: {msg}"


def _header_spacing_note(args, exc) -> str:
    """For a spacing judged swapped or implausible that the user did not give (read from the file's header): where
    it came from and how to override it; MetaImage headers list the fastest (lateral) axis first, a common
    source of a swapped spacing."""
    from femreg.orientation import OrientationError

    if not isinstance(exc, OrientationError) or exc.problem not in ("swapped", "spacing") \
            or not hasattr(args, "spacing") or args.spacing is not None:
        return ""
    paths = [str(v).lower() for v in vars(args).values() if isinstance(v, (str, os.PathLike))]
    meta = any(p.endswith((".mhd", ".mha")) for p in paths)
    return ("; this spacing was read from the file" + (" (a MetaImage header's ElementSpacing lists the lateral "
                                                       "spacing first: lateral, axial)" if meta else "")
            + (TRANSPOSED_FILE_SPACING if getattr(args, "transpose", False) and exc.problem == "swapped" else "")
            + "; --spacing DX DY (axial, lateral) overrides it")


#: Why a spacing read from a file looks swapped under --transpose: the file's spacing goes with its stored axes.
TRANSPOSED_FILE_SPACING = (", and --transpose exchanged it with the file's axes (a file's spacing is taken in the "
                           "order of its stored axes, lines first here; this one looks written axial, lateral "
                           "already)")


def file_spacing_wording(msg: str) -> str:
    """``msg`` of a refusal that judged a spacing the user did not type: its leading ``--spacing DX DY (axial,
    lateral`` says it is the file's (no --spacing was given)."""
    import re

    return re.sub(r"^(.*?)--spacing ([-+\d.e ]+) \(axial, lateral", r"\1the file's spacing \2 (axial, lateral", msg,
                  count=1)


#: Options naming a file (or folder) a subcommand writes: their missing parent folders are created before the
#: command runs, as track's and elastogram's -o folders are (removed again, if still empty, on bad input).
OUTPUT_OPTIONS = ("output", "json", "vtu", "xdmf", "render", "png")


def _output_folders(args) -> list:
    """Create the missing parent folders of the outputs ``args`` names (:data:`OUTPUT_OPTIONS`); returns those
    created, deepest last.  :class:`femreg.errors.InputError` before any work when one cannot be (a file in the
    way, no write permission), instead of an error about a temporary file after the computation."""
    from pathlib import Path

    from femreg.errors import InputError

    made = []
    for name in OUTPUT_OPTIONS:
        value = getattr(args, name, None)
        if not isinstance(value, (str, os.PathLike)) or not str(value):
            continue                    # unset, or a flag (info --json)
        missing, folder = [], Path(value).absolute().parent
        while not folder.exists() and folder != folder.parent:
            missing.append(folder)
            folder = folder.parent
        if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
            why = "is not a folder" if not folder.is_dir() else "is not writable"
            raise InputError(f"cannot write {value}: {folder} {why}")
        for m in reversed(missing):
            m.mkdir()
            made.append(m)
    return made


def _remove_empty(folders) -> None:
    for folder in reversed(folders):
        try:
            folder.rmdir()              # only if still empty
        except OSError:
            pass


# the module attribute the command reads (tests replace it)
_stderr_is_terminal = stderr_is_terminal


#: the probe-geometry flags of register / track / batch, and what a command without them does instead
_GEOMETRY_FLAGS = ("--geometry", "--radius", "--angle-pitch", "--sweep-radius", "--angle-step")
_GEOMETRY_ELSEWHERE = {
    "plot": "the probe geometry is stored in the result",
    "invert": "the probe geometry is stored in the result",
    "measure": "the probe geometry is stored in the result",
    "info": "it names the geometry the file's header states",
}


def _unknown_option_hint(name, command) -> str:
    """Why an option was left over: the command has no such option (not a value count: the words after it are
    its values); for a probe-geometry flag, what the command does instead."""
    cmd = f"femreg {command}" if command else "femreg"
    why = _GEOMETRY_ELSEWHERE.get(command or "", "") if name in _GEOMETRY_FLAGS else ""
    return f" ({cmd} has no {name} option{': ' + why if why else ''}; {cmd} --help lists its options)"


def _extra_hint(argv, extra, command) -> str:
    """Why words were left over: the option before them takes fewer values (``--frames 1 2 3`` for
    ``--frames 1,2,3``); "" when no option precedes them."""
    first = str(extra[0])
    if first.startswith("-") and not first.lstrip("-+.").replace(".", "").isdigit():
        return _unknown_option_hint(first.split("=", 1)[0], command)
    try:
        i = argv.index(extra[0])
    except ValueError:
        return ""
    opt = next((a for a in reversed(argv[:i]) if a.startswith("-") and not a.lstrip("-+.").replace(".", "")
                .isdigit()), None)
    if opt is None:
        return ""
    name = opt.split("=", 1)[0]
    if name == "--frames":
        return (" (--frames takes one selection, counted from 0: 3, 0:10, 0:10:2 or 1,3,5 -- commas, no "
                "spaces)")
    return f" (after {name}: femreg {command or ''} --help gives how many values it takes)".replace("  ", " ")


def main(argv=None) -> int:
    from femreg.errors import InputError, cli_wording
    from femreg.optional import MissingDependencyError

    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    args, extra = parser.parse_known_args(argv)
    if extra:                       # said by the command, with the option the words followed
        print(f"femreg {getattr(args, 'command', None) or ''}".rstrip() + ": error: unrecognized arguments: "
              f"{' '.join(extra)}{_extra_hint(argv, extra, getattr(args, 'command', None))}", file=sys.stderr)
        return 2
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    import warnings

    def one_line(message, category, *_args, **_kwargs):   # a warning is one line, as the errors are
        return f"femreg {args.command}: warning: {' '.join(str(message).split())}\n"

    saved, warnings.formatwarning = warnings.formatwarning, one_line
    from femreg import _kernels

    if _stderr_is_terminal():       # a log or a test reading stderr gets only the command's own lines
        _kernels.notify_cold_cache(lambda text: print(f"femreg {args.command}: {text}", file=sys.stderr, flush=True))
    made = []
    try:
        made = _output_folders(args)
        with cli_wording():         # the library's messages name the command's flags only
            rc = int(args.func(args) or 0)
        if rc == 2:
            _remove_empty(made)
        return rc
    except BrokenPipeError:         # output piped into e.g. `head`, which closed early: not an error of femreg's
        try:                        # no second error when Python flushes stdout at exit
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):   # stdout without a file descriptor (captured): nothing will flush it
            pass
        return 141                  # 128 + SIGPIPE, as for other Unix tools
    except (InputError, ValueError, OSError) as exc:  # OSError: missing file, unwritable output, full disk
        _remove_empty(made)
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        note = _header_spacing_note(args, exc)
        msg = _name_the_files(args, exc, file_spacing_wording(msg) if note else msg) + note
        if getattr(args, "transpose", False):      # the flag given made them look transposed
            from femreg.orientation import transposed_as_told

            msg = transposed_as_told(msg)
        print(f"femreg {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except MissingDependencyError as exc:  # an optional package this subcommand needs; the message names the extra
        print(f"femreg {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"femreg {args.command}: interrupted (finished work is kept)", file=sys.stderr)
        return 130
    finally:
        warnings.formatwarning = saved
        _kernels.notify_cold_cache(None)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
