"""The options of a registration given as text or JSON -- the command line's shared flags (``femreg register`` /
``track`` / ``batch``) and the settings of :mod:`femreg.batch` -- in one place: their names, their defaults
(those of :func:`femreg.register` and :func:`femreg.io.read_frames`), and how they become keyword arguments.
The command line (:mod:`femreg.cli`) reads its defaults from here.
"""
from __future__ import annotations

import inspect

from .errors import InputError
from .regularizers import available_regularizers
from .registration import register

__all__ = ["REGISTRATION_DEFAULTS", "READER_DEFAULTS", "frame_selection", "negative_index", "spacing_value",
           "reader_kwargs", "registration_kwargs", "region_kwargs"]

_SIGNATURE = inspect.signature(register)
#: The registration options and their defaults (``femreg.register``'s; ``hourglass`` None = the strategy's,
#: :mod:`femreg.strategy`; ``roi`` None = "auto", :func:`region_kwargs`), in the command line's order.
REGISTRATION_DEFAULTS = {"regularizer": _SIGNATURE.parameters["regularizer"].default, "alpha": None,
                         "element_size": None, "margin": None, "roi": None, "depth": None, "hourglass": None,
                         "strategy": _SIGNATURE.parameters["strategy"].default,
                         "maxiter": _SIGNATURE.parameters["maxiter"].default,
                         "tol": _SIGNATURE.parameters["tol"].default, "no_orientation_check": False}
#: The reader options of :func:`femreg.io.read_frames` (None: the file's own, or the reader's default).
READER_DEFAULTS = {"variable": None, "shape": None, "dtype": None, "spacing": None, "byte_order": None,
                   "frames": None, "sound_speed": None, "origin": None, "transpose": False,
                   "modulation_frequency": None, "iq_conjugate": False}


def frame_selection(text: str):
    """'3' -> 3, '0:10' / '0:10:2' -> slice, '1,3,5' -> [1, 3, 5]."""
    text = text.strip()
    try:
        if ":" in text:
            parts = [int(p) if p.strip() else None for p in text.split(":")]
            if len(parts) > 3 or (len(parts) == 3 and parts[2] == 0):     # a step of 0 selects nothing
                raise ValueError
            return slice(*parts)
        if "," in text:
            return [int(p) for p in text.split(",") if p.strip()]
        return int(text)
    except ValueError:
        import re

        # a MATLAB or prose range, 1-5 / 1..5: its frames inclusive are the slice K:L+1
        m = re.fullmatch(r"\s*(\d+)\s*(?:-|\.\.)\s*(\d+)\s*", text)
        hint = (f"; frames {m[1]} to {m[2]} are {m[1]}:{int(m[2]) + 1} (a slice's end is left out, frames count "
                f"from 0)" if m and int(m[1]) <= int(m[2]) else "")
        raise InputError(f"bad frame selection {text!r} (use 3, 0:10, 0:10:2 or 1,3,5){hint}") from None


def negative_index(selection):
    """The first negative frame index of a selection of :func:`frame_selection` (an int, a list, or a slice's
    start and end), else None.  Frames are counted from 0 on the command line: a Python-style ``-1`` for the last
    frame is refused rather than read silently (a slice's negative step, which reverses the order, is kept)."""
    if isinstance(selection, slice):
        values = [selection.start, selection.stop]
    elif isinstance(selection, (list, tuple)):
        values = list(selection)
    else:
        values = [selection]
    return next((int(v) for v in values if v is not None and int(v) < 0), None)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def spacing_value(text: str):
    """One spacing in mm from text; 'auto' (or 'header', '-') = None, the file's value."""
    if text.lower() in ("auto", "header", "-"):
        return None
    try:
        v = float(text)
    except ValueError:
        point = text.replace(",", ".", 1) if text.count(",") == 1 else ""
        hint = f": write it with a decimal point, {point}" if point and _is_number(point) else ""
        raise InputError(f"bad spacing {text!r} (mm, or 'auto' to keep the file's){hint}") from None
    if not (v > 0 and v < float("inf")):
        raise InputError(f"spacing must be positive, got {text!r}")
    return v


def reader_kwargs(options) -> dict:
    """The :func:`femreg.io.read_frames` keyword arguments from a mapping of reader options (missing = None)."""
    shape = options.get("shape")
    if shape is not None and len(shape) not in (2, 3):
        raise InputError(f"--shape takes 2 or 3 integers (AXIAL LATERAL or FRAMES AXIAL LATERAL), got {shape}")
    from .io.iq import check_modulation_frequency, check_sound_speed

    c = options.get("sound_speed")
    if c is not None:           # unused by most formats: a number in other units would pass unnoticed
        check_sound_speed(c)
    if options.get("modulation_frequency") is not None:   # in Hz it would upsample each line a million-fold
        check_modulation_frequency(options["modulation_frequency"])
    return dict(variable=options.get("variable"), shape=shape, dtype=options.get("dtype"),
                spacing=options.get("spacing"), byte_order=options.get("byte_order"), frames=options.get("frames"),
                sound_speed=options.get("sound_speed"), modulation_frequency=options.get("modulation_frequency"),
                iq_conjugate=bool(options.get("iq_conjugate")), origin=options.get("origin"),
                transpose=bool(options.get("transpose")))


def registration_kwargs(options) -> dict:
    """Keyword arguments of :func:`femreg.register` / :func:`femreg.track` from a mapping of the registration
    options (:data:`REGISTRATION_DEFAULTS`, missing = the default)."""
    o = {**REGISTRATION_DEFAULTS, **{k: v for k, v in dict(options).items() if k in REGISTRATION_DEFAULTS}}
    es, alpha, name, hourglass = o["element_size"], o["alpha"], o["regularizer"], o["hourglass"]
    if es is not None and len(es) not in (1, 2):
        raise InputError(f"--element-size takes 1 or 2 values (mm), got {es}")
    if es is not None and not all(v > 0 and v < float("inf") for v in es):
        raise InputError(f"--element-size must be > 0 mm, got {' '.join(f'{v:g}' for v in es)}")
    if o["margin"] is not None and not (o["margin"] >= 0 and o["margin"] < float("inf")):
        raise InputError(f"--margin must be a finite number >= 0 (mm), got {o['margin']:g}")
    if o["tol"] is not None and not (o["tol"] > 0 and o["tol"] < float("inf")):
        raise InputError(f"--tol must be a finite number > 0, got {o['tol']:g}")
    if o["maxiter"] is not None and not o["maxiter"] >= 1:     # 0: the initial guess, returned as converged
        raise InputError(f"--maxiter must be an integer >= 1 (Gauss-Newton iterations), got {o['maxiter']}")
    if alpha is not None and alpha != "auto" and not (alpha >= 0 and alpha < float("inf")):
        raise InputError(f"--alpha must be a finite number >= 0, got {alpha}")
    if name not in available_regularizers():
        raise InputError(f"unknown regularizer {name!r}; choose one of {available_regularizers()}")
    opts = {}
    if hourglass is not None:
        if not name.startswith("momentum"):
            raise InputError(f"--hourglass applies to the momentum regularisers, not {name!r}")
        if not (hourglass >= 0 and hourglass < float("inf")):
            raise InputError(f"--hourglass must be a finite number >= 0, got {hourglass}")
        opts["regularizer_options"] = {"hourglass": hourglass}
    return dict(**opts, regularizer=name, alpha=alpha, strategy=o["strategy"],
                element_size=None if es is None else (es[0] if len(es) == 1 else tuple(es)),
                margin=o["margin"], maxiter=o["maxiter"], tol=o["tol"],
                check_orientation=not o["no_orientation_check"], **region_kwargs(o))


def region_kwargs(options) -> dict:
    """``roi`` and ``depth`` of :func:`femreg.register` from a mapping with ``roi`` (4 numbers, 6 for a volume,
    "auto" or "full"; missing or None = "auto") and ``depth`` (2 numbers, mm)."""
    roi = options.get("roi")
    depth = options.get("depth")
    if isinstance(roi, str):
        roi = [roi]
    if roi is None or [str(v).lower() for v in roi] == ["auto"]:
        out = "auto"
    elif [str(v).lower() for v in roi] in (["full"], ["none"]):
        out = None
    else:
        try:
            out = tuple(float(v) for v in roi)
        except (TypeError, ValueError):
            out = ()
        if len(out) not in (4, 6):
            raise InputError(f"--roi takes X0 X1 Y0 Y1 (mm; a volume X0 X1 Y0 Y1 Z0 Z1), auto or full, got "
                             f"{' '.join(map(str, roi))}")
    if depth is not None:
        if roi is not None and out != "auto":
            raise InputError("give --roi or --depth, not both")
        return dict(roi="auto", depth=tuple(float(v) for v in depth))
    return dict(roi=out, depth=None)
