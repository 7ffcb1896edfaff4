"""Flags shared by every command that reads RF frames (``info``, ``register``, ``track``, ``plot``).

Use::

    from femreg.cli._common import add_reader_args, frames_from_args
    def add_parser(sub):
        p = sub.add_parser("mycmd", ...)
        p.add_argument("file")
        add_reader_args(p)
    def run(args):
        fr = frames_from_args(args)          # reads args.file (or pass path=...)
"""
from __future__ import annotations

import argparse
import sys

from .. import options
from ..errors import InputError, SpacingUnknownError
from ..progress import stderr_is_terminal


def _frame_selection(text: str):
    """'3' -> 3, '0:10' / '0:10:2' -> slice, '1,3,5' -> [1, 3, 5] (:func:`femreg.options.frame_selection`)."""
    try:
        return options.frame_selection(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _spacing_value(text: str):
    try:
        return options.spacing_value(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


#: How many values ``--spacing`` takes: axial and lateral for frames, and the elevational plane spacing for volumes.
SPACING_COUNTS = {2: "DX DY", 3: "DX DY DZ"}


class _SpacingAction(argparse.Action):
    """``--spacing``: two values (frames: axial, lateral) or three (volumes: axial, lateral, elevational), mm;
    any other count is argparse's error naming the count given (exit 2).  Three values for frames are refused
    where the file is read (:func:`frames_from_args`), which knows whether it holds volumes."""

    #: the values as help and usage show them (argparse would write "MM [MM ...]"; femreg.cli._Parser reads this)
    usage_metavar = "DX DY [DZ]"

    def __call__(self, parser, namespace, values, option_string=None):
        if len(values) not in SPACING_COUNTS:
            raise argparse.ArgumentError(self, f"expected 2 arguments (DX DY) or 3 for volumes (DX DY DZ), got "
                                               f"{len(values)}")
        setattr(namespace, self.dest, list(values))


def _spacing_word(word: str) -> bool:
    """Whether ``word`` is meant as a spacing value (a number, 'auto' / 'header' / '-', or a mistyped number such as
    0,02, which the option's own error names), not a file or folder given after the option."""
    import re

    word = word.lower()
    return word in ("auto", "header", "-") or re.fullmatch(r"[-+]?[\d.,]+(e[-+]?\d+)?", word) is not None


def spacing_values_first(argv: list) -> list:
    """``argv`` with the words left after ``--spacing``'s values moved before the option: the option takes two or
    three values, and argparse, which cannot tell a value from a file, would give it the files written after it
    (``--spacing 0.02 0.2 ref.npy mov.npy``)."""
    argv = list(argv)
    i = 0
    while i < len(argv):
        if argv[i] != "--spacing":
            i += 1
            continue
        j = i + 1
        while j < len(argv) and _spacing_word(argv[j]):
            j += 1
        k = j
        while k < len(argv) and not (argv[k].startswith("-") and argv[k] != "-"):
            k += 1
        if j > i + 1 and k > j:         # values, then words that are none: those words go before the option
            argv[i:k] = argv[j:k] + argv[i:j]
            i += k - j
        i += 1
    return argv


def add_reader_args(parser: argparse.ArgumentParser, *, group_title: str = "input file options") -> None:
    """Add --variable, --shape, --dtype, --spacing, --origin, --byte-order, --frames, --sound-speed, --iq-frequency,
    --transpose, --iq-conjugate to ``parser``."""
    g = parser.add_argument_group(group_title)
    g.add_argument("--variable", metavar="NAME",
                   help="array name in .npz/.mat files (default: rf or frames, else the only 2D/3D array)")
    g.add_argument("--shape", metavar="N", type=int, nargs="+",
                   help="raw files: AXIAL LATERAL (whole frames read) or FRAMES AXIAL LATERAL")
    g.add_argument("--dtype", metavar="TYPE",
                   help="raw files: sample type float32 (default), float64, int16, uint16, int8, uint8, ...")
    g.add_argument("--spacing", nargs="+", type=_spacing_value, action=_SpacingAction,
                   help="axial and lateral pixel spacing in mm, overriding the file's ('auto' keeps the file's "
                        "value for one of them); required for npy/raw and the lateral pitch of .rf; volumes: "
                        "--spacing DX DY DZ (DZ the elevational plane spacing)")
    g.add_argument("--origin", metavar=("X0", "Y0"), nargs=2, type=float,
                   help="position of the first sample in mm (depth of the first sample, lateral position of the "
                        "first line; convex / sector: the first range and 0), overriding the file's (default the "
                        "file's, else 0 0; a start depth the header states is named by femreg info, and applied "
                        "as the first range of --geometry convex / sector frames)")
    g.add_argument("--byte-order", choices=("little", "big"), help="raw files: byte order (default little)")
    g.add_argument("--frames", metavar="SEL", type=_frame_selection,
                   help="frame selection, counted from 0: 3, 0:10, 0:10:2 or 1,3,5 (default all)")
    g.add_argument("--sound-speed", metavar="C", type=float,
                   help="speed of sound in m/s for the axial spacing of Ultrasonix .rf and the remodulation of IQ "
                        "data (default 1540)")
    g.add_argument("--iq-frequency", metavar="MHZ", type=float, dest="modulation_frequency",
                   help="IQ data (complex samples): the demodulation frequency in MHz; the frames are remodulated "
                        "to RF (UFF files store their own, which this overrides)")
    g.add_argument("--transpose", action="store_true",
                   help="the file stores each frame lines first (lateral x axial, e.g. saved as frame.T or from "
                        "MATLAB): transpose every frame as read; --spacing stays axial, lateral")
    g.add_argument("--iq-conjugate", action="store_true",
                   help="IQ data demodulated with exp(+2 pi i f t), the opposite of the usual sign (the frames say "
                        "so when they need it)")


def reader_kwargs(args) -> dict:
    """The :func:`femreg.io.read_frames` keyword arguments from parsed reader flags."""
    return options.reader_kwargs(vars(args))


def frames_from_args(args, path=None, *, allow_sector: bool = False, check_shape: bool | None = None):
    """Read ``path`` (default ``args.file``) with the reader flags of ``args``; returns :class:`Frames`.  Frames of
    a sector scan (UFF) are refused unless ``allow_sector`` (they are not on a Cartesian grid); raw frames read
    with their two sizes exchanged (:func:`femreg.orientation.check_raw_shape`) and IQ data with their spacings
    exchanged (:func:`femreg.orientation.check_remodulated`) are refused unless
    ``check_shape`` is False (default: unless ``--no-orientation-check``)."""
    from ..io import read_frames
    from ..io.uff import require_cartesian
    from ..orientation import OrientationError, check_raw_shape

    path = path if path is not None else args.file
    if len(getattr(args, "spacing", None) or ()) == 3:
        from pathlib import Path

        who = f"femreg {getattr(args, 'command', '') or ''}".strip()
        if not hasattr(args, "volume"):     # elastogram, batch, plot --reference: frames only
            held = "holds RF volumes" if volumes_only(Path(path)) else "is read as frames (axial, lateral)"
            raise InputError(f"{path}: --spacing with three values (DX DY DZ) is for RF volumes, and {who} takes "
                             f"frames; the file {held} (femreg register and femreg track take volumes)")
        raise InputError(f"{path}: --spacing with three values (DX DY DZ) is for RF volumes; these are read as frames "
                         "(axial, lateral): give --volume to read the file as volumes, or --spacing DX DY")
    if check_shape is None:
        check_shape = not getattr(args, "no_orientation_check", False)
    neg = options.negative_index(getattr(args, "frames", None))
    if neg is not None:     # the frame count for the message: the file read whole, unchecked
        n = read_frames(path, **{**reader_kwargs(args), "frames": None}, check_orientation=False).n_frames
        frame_index(neg, n, path, "--frames")
    fr = read_frames(path, **reader_kwargs(args), check_orientation=check_shape)
    _note_raw_only_flags(fr, path, args)
    _note_spacing_against_fields(fr, path, args)
    _note_region_in_centimetres(fr, path, args)
    if check_shape:
        try:
            check_raw_shape(fr)
        except OrientationError as exc:
            raise OrientationError(f"{path}: {exc}", problem=exc.problem) from None
        _check_frame_size(fr, path, args)
    _note_sampling(fr, path, args, check_shape)      # after the refusals: a refused spacing gets one line
    return fr if allow_sector else require_cartesian(fr, f"femreg {getattr(args, 'command', '')}".strip())


def _note_sampling(fr, path, args, checked: bool) -> None:
    """On stderr: the notes of :func:`femreg.orientation.check_sampling` (the carrier a little off the header's
    transmit frequency), and for ``track`` and ``elastogram``, whose pairs' messages are not printed, a carrier
    outside clinical probes' band (:func:`femreg.orientation.frequency_note`, which ``register`` puts in its
    message); once per file and text."""
    import numpy as np

    from ..orientation import carrier_frequency, frequency_note

    meta = fr.metadata or {}
    notes = list(meta.get("sampling_notes") or [])
    if checked and not notes and getattr(args, "command", None) in ("track", "elastogram") \
            and fr.spacing is not None and "iq" not in meta and not np.iscomplexobj(fr.frames):
        from ..orientation import diagnose

        note = frequency_note(carrier_frequency(fr.frames[0], fr.spacing[0]))
        # spacings exchanged or frames transposed: the refusal that follows names them, not an axial value
        if note and diagnose(np.asarray(fr.frames[0]), fr.spacing).problem in ("swapped", "transposed"):
            note = ""
        notes += [f"{path}: {note}"] if note else []
    who = " ".join(["femreg", getattr(args, "command", None) or ""]).strip()
    for note in notes:
        if (str(path), note) not in _NOTED:
            _NOTED.add((str(path), note))
            print(f"{who}: note: {note}", file=sys.stderr)


def _dtype_name(dtype) -> str:
    """numpy's name of a --dtype word (``short`` -> ``int16``), the word itself where it names none."""
    from ..io.checks import parse_dtype

    try:
        return parse_dtype(dtype).name
    except (InputError, TypeError, ValueError):
        return str(dtype).lower()


def _note_raw_only_flags(fr, path, args) -> None:
    """On stderr: --shape, --dtype or --byte-order given for a file that states its own (npy, npz, mat, ...) and
    read otherwise; the file's header wins, but a flag that is silently ignored hides a wrong idea of the data."""
    meta = fr.metadata or {}
    formats = f"{meta.get('format', '')} {(meta.get('file_metadata') or {}).get('format', '')}"
    if "raw" in formats:
        return
    stored = str(meta.get("stored_dtype") or (meta.get("file_metadata") or {}).get("stored_dtype") or "")
    ignored = []
    shape = getattr(args, "shape", None)
    if shape and tuple(int(v) for v in shape[-2:]) != tuple(fr.shape):
        ignored.append(f"--shape {' '.join(str(v) for v in shape)} (the file's frames: {fr.n_frames} x "
                       f"{fr.shape[0]} x {fr.shape[1]})")
    dtype = getattr(args, "dtype", None)
    if dtype and stored and _dtype_name(dtype) != stored.lower():
        ignored.append(f"--dtype {dtype} (stored as {stored})")
    if getattr(args, "byte_order", None):
        ignored.append(f"--byte-order {args.byte_order}")
    key = (str(path), tuple(ignored))
    if ignored and key not in _NOTED:
        _NOTED.add(key)
        who = " ".join(["femreg", getattr(args, "command", None) or ""]).strip()
        print(f"{who}: note: {path}: {'; '.join(ignored)} ignored: they apply to headerless raw files, and this "
              f"{meta.get('format', 'file')} file states its own", file=sys.stderr)


#: A given --spacing further than this (relative) from what the file's fields imply is noted.
FIELD_SPACING_TOLERANCE = 0.05


def _note_spacing_against_fields(fr, path, args) -> None:
    """On stderr: a typed --spacing that differs from the one the file's header fields imply (``fs``, ``c``,
    ``pitch``: :func:`femreg.io.checks.spacing_suggestion`) by more than :data:`FIELD_SPACING_TOLERANCE`.  Only a
    note: the fields can be wrong too (a sampling rate before decimation), but a spacing off by a quarter puts
    every depth and lateral position a quarter off without any other sign."""
    import numpy as np

    from ..io.checks import spacing_suggestion

    given = getattr(args, "spacing", None)
    fields = (fr.metadata or {}).get("fields")
    if given is None or not fields or fr.spacing is None or getattr(args, "spacing_stand_in", False):
        return
    sug = spacing_suggestion(fields)
    if sug is None:
        return
    from ..orientation import iq_decimation

    off, tol = [], FIELD_SPACING_TOLERANCE
    read = [float(v) for v in np.ravel(fr.spacing)[:2]]
    iq = (fr.metadata or {}).get("iq") or {}
    if iq.get("iq_spacing_mm"):         # remodulated IQ: the given spacing is the IQ samples', a whole decimation
        read[0] = float(iq["iq_spacing_mm"])
    try:
        implied = [float(sug.dx), float(sug.dy)]
    except (TypeError, ValueError):     # "DX" / "DY" / "auto": the fields do not say both
        implied = [None, None]
    if None not in implied and any(all(abs(r / (i * k) - 1.0) <= tol for r, i in zip(order, implied))
                                   for order in (read[::-1], read) for k in (1.0, 1e-3, 1e3, 0.1, 10.0)
                                   if not (order is read and k == 1.0)):
        return                          # exchanged or in other units: the orientation checks say so, better
    for axis, name in enumerate(("axial", "lateral")):
        try:
            i = float((sug.dx, sug.dy)[axis])
        except (TypeError, ValueError):
            continue
        ratio = read[axis] / i
        units = any(abs(ratio / k - 1.0) <= tol for k in (1e-3, 1e3, 0.1, 10.0))   # the units checks name them
        typed = given[axis]
        if axis == 0 and iq and iq_decimation(read[0], i):
            continue                    # IQ decimated after sampling: femreg.orientation.check_sampling notes it
        if typed is not None and str(typed) != "auto" and abs(ratio - 1.0) > tol and not units:
            off.append(f"{name} {read[axis]:g} mm against {i:g}")
    key = (str(path), "fields", tuple(off))
    if off and key not in _NOTED:
        _NOTED.add(key)
        who = " ".join(["femreg", getattr(args, "command", None) or ""]).strip()
        print(f"{who}: note: {path}: --spacing differs from what the file's fields imply ({'; '.join(off)}: "
              f"{sug.why_x}; {sug.why_y}): every depth and lateral position scales with it; check it against the "
              f"scanner's settings", file=sys.stderr)


#: A --depth / --roi span under this share of the frame's along each axis it limits, whose ten times lies inside
#: the frame, is noted as likely given in centimetres.
CM_REGION_SHARE = 0.25


def _note_region_in_centimetres(fr, path, args) -> None:
    """On stderr: a --depth or --roi that reads as centimetres (a scanner's display gives depths in cm): a small
    part of the frame (under :data:`CM_REGION_SHARE` of it along each axis given) whose values times ten lie inside
    the frame.  Only a note: a small region can be meant, but one in cm registers a strip of the near field."""
    import numpy as np

    depth, roi = getattr(args, "depth", None), getattr(args, "roi", None)
    a = np.asarray(getattr(fr, "frames", None))
    if fr.spacing is None or len(fr.spacing) != 2 or a.ndim != 3:
        return
    if depth is not None:
        flag, vals, axes = "--depth", [float(v) for v in depth], (0,)
    elif roi is not None and len(roi) == 4:
        try:
            flag, vals, axes = "--roi", [float(v) for v in roi], (0, 1)
        except (TypeError, ValueError):     # auto / full
            return
    else:
        return
    lo = [float(fr.origin[k]) for k in (0, 1)]
    hi = [lo[k] + float(fr.spacing[k]) * (a.shape[1 + k] - 1) for k in (0, 1)]
    small = all(abs(vals[2 * k + 1] - vals[2 * k]) < CM_REGION_SHARE * (hi[k] - lo[k]) for k in axes)
    fits = all(lo[k] <= 10 * v <= hi[k] for k in axes for v in vals[2 * k: 2 * k + 2])
    key = (str(path), flag, tuple(vals))
    if small and fits and key not in _NOTED:
        _NOTED.add(key)
        who = " ".join(["femreg", getattr(args, "command", None) or ""]).strip()
        extent = " x ".join(f"{h - lo_:.3g}" for lo_, h in zip(lo, hi))
        print(f"{who}: note: {path}: {flag} {' '.join(f'{v:g}' for v in vals)} (mm) is a small part of the "
              f"{extent} mm frame: in centimetres it would be {flag} {' '.join(f'{10 * v:g}' for v in vals)} "
              "(mm)", file=sys.stderr)


#: Notes already given in this process (register reads the same file's flags for each frame file).
_NOTED: set = set()


def frames_on_result_grid(args, path, result_spacing, result_shape=None):
    """Frames of ``path`` drawn or used on a result's pixel grid (``plot --reference``, ``invert --images``): a
    file that stores no spacing takes the result's (``result_spacing``, mm), no --spacing needed; a spacing that
    differs from it by more than 1 % is refused (another recording, or a wrong --spacing).  IQ frames take the IQ
    sample spacing whose remodulation gives the result's grid (``result_shape``, (axial, lateral) pixels:
    :func:`_iq_stand_in`)."""
    import numpy as np

    from ..errors import SpacingUnknownError

    res_sp = np.ravel(np.asarray([] if result_spacing is None else result_spacing, float))
    try:
        fr = frames_from_args(args, path)
    except SpacingUnknownError as exc:
        if args.spacing is not None or res_sp.size != 2:
            raise
        args.spacing = _iq_stand_in(args, exc.frame_shape, [float(v) for v in res_sp], result_shape)
        fr = frames_from_args(args, path)
    sp = None if fr.spacing is None else np.ravel(np.asarray(fr.spacing, float))
    if res_sp.size == 2 and sp is not None and sp.size == 2 and not np.allclose(sp, res_sp, rtol=0.01):
        # the file's own spacing exchanged: its frames are stored lines first (a --spacing given swapped is not)
        exchanged = np.allclose(sp[::-1], res_sp, rtol=0.01)
        lines_first = exchanged and args.spacing is None and not getattr(args, "transpose", False)
        typed_swapped = exchanged and args.spacing is not None
        raise InputError(f"{path}: spacing {tuple(float(v) for v in sp)} mm differs from the result's "
                         f"{tuple(float(v) for v in res_sp)} (axial, lateral): "
                         + ("exchanged, as for frames stored lines first: pass --transpose" if lines_first else
                            "the axial and lateral spacings look swapped: leave --spacing out (the result's is "
                            f"used) or pass --spacing {res_sp[0]:g} {res_sp[1]:g}" if typed_swapped else
                            "not the frames it was registered from, or a wrong --spacing (leave it out: the "
                            "result's is used)"))
    return fr


def _iq_stand_in(args, frame_shape, res_sp, result_shape):
    """The spacing that stands in for a file's missing one on a result's grid: ``res_sp`` (mm), but for IQ frames
    (``--iq-frequency``) the spacing of the IQ samples, the result's axial step times the upsampling of the
    remodulation, ``up = (n_rf - 1) / (n_iq - 1)`` (:func:`femreg.io.iq.remodulate`); with the RF step as the IQ
    step the phases would be read for a frequency ``up`` times too high and the frames refused.  ``frame_shape``:
    the (axial, lateral) samples the reader found (:class:`femreg.errors.SpacingUnknownError`), so that the file
    is not read again to count them."""
    if (getattr(args, "modulation_frequency", None) is None or result_shape is None or frame_shape is None
            or len(frame_shape) != 2):
        return res_sp
    # --transpose: the file's lateral axis holds the samples
    n_iq, n_rf = int(frame_shape[1] if getattr(args, "transpose", False) else frame_shape[0]), int(result_shape[0])
    if n_iq > 1 and n_rf > n_iq and (n_rf - 1) % (n_iq - 1) == 0:
        return [res_sp[0] * ((n_rf - 1) // (n_iq - 1)), res_sp[1]]
    return res_sp


def frame_index(index: int, n: int, path, flag: str) -> int:
    """``index`` of a frame (``flag`` names the option that gave it) in ``path`` holding ``n`` frames; an
    InputError (exit 2) naming the valid range when it is outside 0 to n - 1.  A negative index is refused, not
    read Python-style from the end: the command line counts frames from 0 everywhere (--pair, --frames, --frame)."""
    index = int(index)
    if 0 <= index < n:
        return index
    why = " (a negative index is not counted from the end)" if index < 0 else ""
    raise InputError(f"{path}: {flag}: no frame {index}: the file holds {n} frame(s), counted from 0: 0 to "
                     f"{n - 1}{why}")


#: Lateral speckle narrower than this many axial RF periods over a whole frame: no spacing order explains it (a
#: swap reads 0.04-0.29 and is said so, :mod:`femreg.orientation`); the units are wrong (0.0001 typed for 0.1 mm:
#: 0.01).
IMPLAUSIBLE_CELL_PERIODS = 0.1


def _check_frame_size(fr, path, args) -> None:
    """A whole frame of a linear array as read from ``path``: refuse a spacing in centimetres, which the RF checks
    of register cannot see on a crop (:func:`femreg.orientation.diagnose`, ``whole_frame``); only that rule here,
    the other checks stay where they were."""
    import numpy as np

    from ..orientation import OrientationError, diagnose

    a = np.asarray(getattr(fr, "frames", None))
    linear = getattr(args, "geometry", None) in (None, "linear") and not getattr(args, "volume", False)
    if not linear or a.ndim != 3 or "iq" in fr.metadata or fr.spacing is None or len(fr.spacing) != 2:
        return
    rep = diagnose(a[0], fr.spacing, whole_frame=True)
    if rep.small_frame:
        raise OrientationError(f"{path}: {rep.message}", problem=rep.problem)
    if rep.problem == "spacing" and np.isfinite(rep.cell_periods) and rep.cell_periods < IMPLAUSIBLE_CELL_PERIODS:
        # a lateral pitch in metres (a header's pitch copied as it stands): before register's own check, which runs
        # on the echo's crop, the echo finder refused a frame 0.03 mm wide as "too small for a mesh"
        from ..io.checks import spacing_suggestion

        fields = (fr.metadata or {}).get("fields") or {}
        sug = spacing_suggestion(fields) if fields else None
        hint = f"; {sug.text()}" if sug is not None and "DX" not in (sug.dx, sug.dy) else ""
        n, dy = a.shape[2], float(fr.spacing[1])
        width = f" (the {n} lines then span {n * dy:.3g} mm)" if n * dy < 1.0 else ""
        raise OrientationError(f"{path}: {rep.message}{width}{hint}", problem=rep.problem)


def beam_spacing_error(exc, geometry):
    """A reader's "spacing unknown" error said for convex / sector frames, whose only spacing is the range step
    (``--spacing DX auto``); other errors as they are."""
    if not isinstance(exc, SpacingUnknownError):
        return exc
    s = exc.suggestion
    hint = f"; its fields suggest DX = {s.dx} ({s.why_x}): check it against the scanner's settings" if s else ""
    where = str(exc).split(": ", 1)[0] if exc.path is None else exc.path
    return InputError(f"{where}: the range step (the axial spacing, mm) is not in the file: pass --spacing DX auto "
                      f"(--geometry {geometry.kind}: the rays are --angle-pitch apart){hint}")


def beam_frames_from_args(args, geometry, path=None):
    """Frames of a convex / sector file (``--geometry convex|sector``): ``(Frames, dr, (r0, 0))`` with the range
    step ``dr`` mm and the first sample's range ``r0`` mm of the file (or ``--spacing``).  The rays lie
    ``geometry.angle_pitch_deg`` apart, so no lateral spacing is needed: with ``--spacing DX auto``, or a file that
    stores none, the frames carry the angle pitch (deg) as their lateral spacing (the convention of
    :class:`femreg.geometry.BeamResult`)."""
    sp = beam_spacing_args(args, geometry)
    try:
        fr = frames_from_args(argparse.Namespace(**dict(vars(args), spacing=sp)), path)
    except InputError as exc:
        raise beam_spacing_error(exc, geometry) from None
    return fr, float(fr.spacing[0]), (float(fr.origin[0]), 0.0)


def beam_spacing_args(args, geometry) -> list:
    """``--spacing`` for convex / sector frames: ``[DX or None, angle pitch]`` (the lateral value is not used; one
    given is reported so on stderr)."""
    sp = list(args.spacing) if getattr(args, "spacing", None) else [None, None]
    pitch = float(geometry.angle_pitch_deg)
    if sp[1] is not None and abs(sp[1] - pitch) > 1e-6 * pitch:
        who = " ".join(["femreg", getattr(args, "command", None) or ""]).strip()
        print(f"{who}: note: --geometry {geometry.kind}: the lateral spacing {sp[1]:g} is not used (the rays are "
              f"--angle-pitch {pitch:g} deg apart)", file=sys.stderr)
    return [sp[0], pitch]


def _alpha_arg(text):
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number or 'auto', got {text!r}") from None


def ncc_arg(text):
    """``--min-ncc``: a correlation, -1 to 1 (a threshold above 1 would flag every pair after all the work)."""
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not -1.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"an NCC lies in -1 to 1, got {text!r}")
    return v


def add_registration_args(parser: argparse.ArgumentParser) -> None:
    """Flags shared by ``register`` and ``track``: regulariser, alpha, mesh and solver settings."""
    from ..regularizers import available_regularizers

    g = parser.add_argument_group("registration options")
    defaults = options.REGISTRATION_DEFAULTS
    g.add_argument("-r", "--regularizer", default=defaults["regularizer"], metavar="NAME",
                   help="regulariser: " + ", ".join(available_regularizers())
                        + f" (default {defaults['regularizer']})")
    g.add_argument("--alpha", type=_alpha_arg, metavar="ALPHA|auto",
                   help="regulariser weight (default: the regulariser's documented one); 'auto' chooses it from the "
                        "first pair without ground truth (femreg.autoalpha, several registrations)")
    g.add_argument("--element-size", metavar="MM", type=float, nargs="+",
                   help="element size in mm (one value, or axial and lateral)")
    g.add_argument("--margin", type=float, help="strip of the image left out of the mesh, mm")
    g.add_argument("--roi", nargs="+", metavar=("X0 X1 Y0 Y1|auto|full", "Z0 Z1"),
                   help="region registered, mm (axial x0 x1, lateral y0 y1; a volume also elevational z0 z1); "
                        "default auto: where the frames hold "
                        "usable echo (depth or lines at the noise floor and saturated samples left out, and said "
                        "so); full: the whole frames")
    g.add_argument("--depth", nargs=2, type=float, metavar=("D0", "D1"),
                   help="depth range registered, mm, over all lines (instead of --roi; volumes too)")
    g.add_argument("--hourglass", type=float, default=None, metavar="W",
                   help="momentum regularisers only: hourglass control weight relative to alpha (default with "
                        "--strategy auto: femreg.strategy.DEFAULT_HOURGLASS for a pair, 1000 for R_P_sigma, "
                        "femreg.sequence.TRACK_HOURGLASS for the increments of track; 0 = the paper's with "
                        "--strategy paper)")
    g.add_argument("--strategy", choices=("auto", "paper"), default=defaults["strategy"],
                   help="auto (default): speckle-sized mesh, coarse-to-fine start, peak-hopping repair; paper: the "
                        "paper's procedure (5 x 9 mm block matching, 2 mm mesh)")
    g.add_argument("--maxiter", type=int, default=defaults["maxiter"],
                   help=f"Gauss-Newton iterations (default {defaults['maxiter']})")
    g.add_argument("--tol", type=float, default=defaults["tol"],
                   help=f"stop when ||du||/||u|| < TOL (default {defaults['tol']:g})")
    g.add_argument("--no-orientation-check", action="store_true",
                   help="skip the check that refuses frames that look transposed (lines x samples) or a spacing "
                        "that looks swapped, judged from the RF carrier (femreg.orientation)")


def registration_kwargs(args) -> dict:
    """Keyword arguments of :func:`femreg.register` / :func:`femreg.track` from the registration flags."""
    return options.registration_kwargs(vars(args))


def region_kwargs(args) -> dict:
    """``roi`` and ``depth`` of :func:`femreg.register` from ``--roi`` (4 numbers, auto or full) and ``--depth``
    (:func:`femreg.options.region_kwargs`)."""
    return options.region_kwargs(vars(args))


def failed_notice(path, success, message, flag="") -> int:
    """After drawing: say when the result drawn is a failed or flagged computation (exit 1), else 0."""
    import sys

    import numpy as np

    if isinstance(success, (bool, int, np.bool_)) and not success and message:   # no message: made by hand
        msg = str(message)
        kind = "FLAGGED" if msg.startswith("FLAGGED") else "FAILED"     # say it once, as the result does
        reason = msg.removeprefix("FAILED: ").removeprefix("FLAGGED: ")
        print(f"femreg plot: {kind}: {path} holds a {kind.lower()} result, drawn as such: {reason}", file=sys.stderr)
        return 1
    if flag:
        print(f"femreg plot: FLAGGED: {path}: {flag}", file=sys.stderr)
        return 1
    return 0


def file_frame(selection, k: int) -> int:
    """The file's index of frame ``k`` of a ``--frames`` selection (counted from 0, as the run counts them): a
    list's k-th entry, a slice's start + k x step (negative indices are refused before)."""
    if isinstance(selection, slice):
        return (selection.start or 0) + k * (selection.step or 1)
    if isinstance(selection, (list, tuple)):
        return int(selection[k])
    return int(selection) + k


def registered_frames(path, res=None):
    """``(i, j, what)``: the file's frames a result file was registered from, reference i and moving j, and the
    words saying so; None when the file does not say.  A pair of ``femreg register FILE --pair I J`` / ``femreg
    batch`` (its ``pair``); frame K of a ``femreg track`` run: frames 0 -> K (accumulate or direct, both in
    frame 0's coordinates), through its ``track.json``'s ``file_frames`` when the run took a --frames
    selection.  ``res``: the file's arrays when already read."""
    import json
    from pathlib import Path

    import numpy as np

    if res is None:
        with np.load(path, allow_pickle=False) as z:
            res = {k: z[k] for k in ("pair", "frame", "increment") if k in z.files}
    pair = np.ravel(res["pair"]) if res.get("pair") is not None else np.empty(0)
    if pair.size == 2:
        return int(pair[0]), int(pair[1]), f"registered frames {int(pair[0])} -> {int(pair[1])}"
    if "frame" not in res or "increment" not in res:
        return None
    k = int(np.ravel(res["frame"])[0])
    try:
        frames = json.loads((Path(path).parent / "track.json").read_text()).get("file_frames")
    except (OSError, ValueError):
        frames = None
    if frames and k < len(frames):
        return (int(frames[0]), int(frames[k]), f"is frame {k} of a track run on the file's frames "
                f"{frames[0]}-{frames[-1]}: frames {frames[0]} -> {frames[k]} of the file")
    return 0, k, f"is frame {k} of a track run: frames 0 -> {k}"


def _record_file_frames(folder, frames) -> None:
    """Add the file's indices of a --frames selection to ``folder/track.json`` (``file_frames``), so that
    ``femreg plot --reference FILE`` draws the B-mode of the frame the run starts from."""
    import json
    from pathlib import Path

    from .._atomic import atomic_write_text

    path = Path(folder) / "track.json"
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return
    record["file_frames"] = [int(k) for k in frames]
    atomic_write_text(path, json.dumps(record, indent=1))


def run_tracking(args, call, noun: str, total: int | None = None) -> int:
    """Run ``call(on_frame)`` (a tracking run writing one file per frame into ``args.output``), print a line per
    frame and the run's summary; the exit code: 0 done, 1 a frame flagged or failed (finished frames kept, the
    message says how to resume); bad input (:class:`InputError`) propagates (exit 2).  ``noun``: "frame" or
    "volume", for the summary; ``total``: the number of frames registered (frames - 1), named in each line.

    With progress on and stderr not a terminal (a log, a pipe) the per-frame line is the progress: it carries
    the count and the elapsed time, and the run draws no progress lines of its own (``reports_progress``)."""
    import time

    done = []
    start = time.monotonic()
    as_progress = not args.no_progress and not stderr_is_terminal()
    sel = getattr(args, "frames", None)
    # a selection counts its own frames from 0: the line names the file's frame too, where they differ
    moved = sel is not None and any(file_frame(sel, k) != k for k in range(1, (total or 0) + 1))

    def on_frame(k, res, flag):
        done.append(k)
        count = f" ({len(done)}/{total}, {time.monotonic() - start:.1f} s)" if as_progress and total else ""
        rep = getattr(res, "repeats", None)
        what = (f"repeats {noun} {rep} (identical samples): not registered, {noun} {rep}'s field kept" if rep is not None
                else f"ncc {res.ncc_before:.3f} -> {res.ncc_after:.3f}, nit {res.nit}")
        if getattr(res, "retried", ""):     # the start from the previous increment was flagged
            what += ", retried from a fresh start"
        elif getattr(res, "started_afresh", False):     # femreg.initial.previous_or_fresh
            what += ", started afresh (no motion matched better than the previous increment)"
        # with the progress bar on, the per-frame line goes to stderr beside the bar
        where = f" (the file's frame {file_frame(sel, k)})" if moved else ""
        print(f"{noun} {k:3d}{where}: {what}{count}" + (f"  FLAGGED: {flag}" if flag else ""),
              file=sys.stdout if args.no_progress else sys.stderr)

    on_frame.reports_progress = True

    try:
        out = call(on_frame)
    except InputError:
        raise  # bad input: one line and exit 2 from the dispatcher
    except Exception as exc:  # noqa: BLE001 - a frame failed: say which, and that finished frames are kept
        k = (done[-1] if done else 0) + 1
        msg = " ".join(str(exc).split()) or type(exc).__name__
        kept = f"{noun}s 1-{k - 1} are saved in {args.output}" if k > 1 else f"no {noun} was finished"
        print(f"femreg track: failed: {noun} {k} could not be computed ({type(exc).__name__}: {msg}); {kept}; "
              f"rerun with --resume to continue", file=sys.stderr)
        return 1
    if len(out) and getattr(out[0], "excluded", None):
        print(f"femreg track: left out of the mesh (the rest is registered): {out[0].excluded}")
    repeated = list(getattr(out, "repeated", ()))
    if repeated:            # a recording that writes frames twice: say so once, with the frames
        from ..image import repeats_listed

        shown = repeats_listed(repeated)
        one = len(repeated) == 1
        print(f"femreg track: note: {len(repeated)} {noun}{'' if one else 's'} {'repeats' if one else 'repeat'} "
              f"the one before (identical samples; {noun}s {shown}): not registered, the field before kept")
    if sel is not None:
        _record_file_frames(args.output, [file_frame(sel, k) for k in range(len(out) + 1)])
    if moved:
        print(f"femreg track: note: --frames selected the file's frames "
              f"{', '.join(str(file_frame(sel, k)) for k in range(len(out) + 1))}: frame K and {args.output}/"
              f"frame_KKK.npz count the selection from 0")
    n_new = sum(out.computed)
    n_flag = sum(1 for f in out.flags if f)
    retried = list(getattr(out, "retried", ()))
    again = (f", {len(retried)} retried from a fresh start ({noun}{'' if len(retried) == 1 else 's'} "
             f"{', '.join(map(str, retried))})") if retried else ""
    print(f"femreg track: {len(out)} {noun}{'' if len(out) == 1 else 's'} in {args.output} ({n_new} computed, "
          f"{len(out) - n_new} resumed, {n_flag} flagged{again})")
    if n_flag:
        first = next(k for k, f in enumerate(out.flags, start=1) if f)
        hint = ""
        # (volumes have no block matching: their flagged increments were already retried from their pyramid)
        if (noun == "frame" and getattr(args, "init", None) == "previous"
                and getattr(args, "mode", None) == "accumulate" and any("peak hopping" in f for f in out.flags if f)):
            # a freehand loop's compression per frame varies: the previous increment can start a whole RF period off
            hint = ("; each increment started from the previous one (--init previous): where the compression per "
                    "frame varies, as in a freehand loop, --init blockmatch starts each afresh")
        print(f"femreg track: FLAGGED: {n_flag} of {len(out)} {noun}(s) (frame {first}: {out.flags[first - 1]})"
              f"{hint}", file=sys.stderr)
        return 1
    return 0


def array_headers(path) -> dict:
    """{name: (shape, dtype)} of the arrays in an .npz or .mat file (MATLAB order for .mat), read from headers
    only, without loading the data ({} for other files, or when the headers cannot be read)."""
    import zipfile
    from pathlib import Path

    import numpy as np

    path, out = Path(path), {}
    try:
        if path.suffix.lower() == ".npz":
            with zipfile.ZipFile(path) as zf:
                for info in zf.infolist():
                    with zf.open(info) as fh:
                        version = np.lib.format.read_magic(fh)
                        read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                                else np.lib.format.read_array_header_2_0)
                        shape, _, dtype = read(fh)
                    out[info.filename.removesuffix(".npy")] = (tuple(shape), str(dtype))
        elif path.suffix.lower() == ".mat":
            from ..io.matlab import mat_version

            from ..io.mat5 import read_mat5, shown_text
            from ..io.matlab import text73

            version = mat_version(path)
            if version == "7.3":
                import h5py

                with h5py.File(path, "r") as h5:
                    for k, v in h5.items():
                        if hasattr(v, "shape"):
                            cls = v.attrs.get("MATLAB_class", b"")
                            cls = cls.decode("ascii", "replace") if isinstance(cls, bytes) else str(cls)
                            text = text73(v) if cls == "char" and v.size <= 4096 else None
                            out[k] = (tuple(v.shape[::-1]), "char " + shown_text(text) if text is not None
                                      else str(v.dtype))
            elif version == "5":        # a char variable with its text (scipy's whosmat gives it shape (1,))
                order, variables = read_mat5(path, path.read_bytes())
                for v in variables:
                    out[v.name] = (tuple(v.shape), f"{v.cls} {shown_text(v.text)}" if v.text is not None else v.cls)
            else:
                from scipy.io import whosmat

                for name, shape, cls in whosmat(str(path)):
                    out[name] = (tuple(shape), str(cls))
    except Exception:  # noqa: BLE001 - the listing is a courtesy; the reader's own error stays the verdict
        return out
    return out


def add_volume_arg(p) -> None:
    """``--volume`` of ``register`` and ``track``: read the file(s) as RF volumes."""
    p.add_argument("--volume", action="store_true",
                   help="read the file(s) as RF volume(s): a 3D array is one volume (axial, lateral, elevational), "
                        "a 4D one a sequence; spacing (dx, dy, dz) from the file (a MetaImage of NDims 3 is "
                        "otherwise read as a stack of frames); files that can only hold volumes (4D data, three "
                        "spacing values) are read so without it")


def volumes_only(p: Path) -> bool:
    """Whether ``p`` can only hold volumes, judged from its header without reading the data: a MetaImage of NDims
    4, or a MAT-file whose ``spacing`` has 3 values or that holds a 4D array (the frame reader refuses both)."""
    suffix = p.suffix.lower()
    if not p.is_file() or suffix not in (".mhd", ".mha", ".mat"):
        return False
    if suffix in (".mhd", ".mha"):
        from ..errors import FileFormatError
        from ..io.metaimage import _parse_header

        try:
            fields = _parse_header(p)[0]
        except FileFormatError:
            return False            # the frame reader says what is wrong with it
        return fields.get("ndims", "").strip() == "4"
    import numpy as np

    from ..io.matlab import frames_shape

    shapes = {k: shape for k, (shape, _) in array_headers(p).items()}
    # (axial, lateral, 1, frame), a Verasonics IData / ImgData with its one section, holds frames
    return int(np.prod(shapes.get("spacing", (0,)))) == 3 or any(len(s) == 4 and len(frames_shape(s)) == 4
                                                                  for s in shapes.values())
