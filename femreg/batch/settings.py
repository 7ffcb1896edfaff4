"""The settings schema of :mod:`femreg.batch`: the task's settings (``task``, ``pairs``, ``mode``, ``grid``,
``init``, ``min_ncc``) and the registration and reader options shared with the command line
(:mod:`femreg.options`), their defaults, and their validation.
"""
from __future__ import annotations

import json

from ..errors import InputError
from ..options import (READER_DEFAULTS, REGISTRATION_DEFAULTS, frame_selection, reader_kwargs,
                       registration_kwargs, spacing_value)

__all__ = ["flag_defaults", "settings_keys", "default_settings", "frames_text"]


_TASK_DEFAULTS = {"task": "track", "pairs": [[0, 1]], "mode": "accumulate", "grid": "current", "init": "previous",
                  "min_ncc": 0.5}


def flag_defaults() -> tuple:
    """({registration option: default}, {reader option: default}) (:mod:`femreg.options`): the settings a batch
    shares with the flags of ``femreg register`` / ``track``, with the same defaults."""
    return dict(REGISTRATION_DEFAULTS), dict(READER_DEFAULTS)


def settings_keys() -> tuple:
    """Names of the settings a job (and a per-recording settings file) may set: the task's, then the shared
    registration and reader flags' (``--element-size`` -> ``element_size``)."""
    reg, reader = flag_defaults()
    return tuple(_TASK_DEFAULTS) + tuple(reg) + tuple(reader)


def default_settings() -> dict:
    """Every setting at its default: the defaults of the shared command-line flags, and ``task="track"``,
    ``pairs=[[0, 1]]``, ``mode="accumulate"``, ``grid="current"``, ``init="previous"``, ``min_ncc=0.5``."""
    reg, reader = flag_defaults()
    return json.loads(json.dumps({**_TASK_DEFAULTS, **reg, **reader}))  # a deep copy


def frames_text(sel):
    """A parsed frame selection back to its JSON form (int, list, or the 'a:b:c' text)."""
    if isinstance(sel, slice):
        return ":".join("" if v is None else str(v) for v in (sel.start, sel.stop, sel.step))
    if isinstance(sel, (list, tuple)):
        return [int(v) for v in sel]
    return sel


def _check_settings(settings: dict, where: str) -> dict:
    """Validate a flat settings dict (JSON types) with the command line's own checks; returns
    (reader kwargs, registration kwargs) for :func:`femreg.io.read_frames` and :func:`femreg.register`."""
    unknown = sorted(set(settings) - set(settings_keys()))
    if unknown:
        raise InputError(f"{where}: unknown setting(s) {unknown}; known: {', '.join(settings_keys())}")
    s = dict(settings)
    def real(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    types = {"alpha": real, "margin": real, "hourglass": real, "tol": real, "sound_speed": real, "min_ncc": real,
             "modulation_frequency": real, "iq_conjugate": lambda v: isinstance(v, bool),
             "maxiter": lambda v: isinstance(v, int) and not isinstance(v, bool),
             "element_size": lambda v: real(v) or (isinstance(v, (list, tuple)) and all(real(x) for x in v)),
             "shape": lambda v: isinstance(v, (list, tuple)) and all(isinstance(x, int) for x in v),
             "regularizer": lambda v: isinstance(v, str), "variable": lambda v: isinstance(v, str),
             "roi": lambda v: isinstance(v, str) or (isinstance(v, (list, tuple)) and all(real(x) for x in v)),
             "depth": lambda v: isinstance(v, (list, tuple)) and len(v) == 2 and all(real(x) for x in v),
             "strategy": lambda v: isinstance(v, str), "no_orientation_check": lambda v: isinstance(v, bool),
             "transpose": lambda v: isinstance(v, bool),
             "dtype": lambda v: isinstance(v, str), "byte_order": lambda v: v in ("little", "big"),
             "frames": lambda v: isinstance(v, (int, str)) or (isinstance(v, (list, tuple))
                                                               and all(isinstance(x, int) for x in v))}
    bad = [k for k, ok in types.items() if s.get(k) is not None and not ok(s[k])]
    if bad:
        raise InputError(f"{where}: bad value(s) " + ", ".join(f"{k}={s[k]!r}" for k in bad))
    if s.get("spacing") is not None:
        sp = s["spacing"]
        if not (isinstance(sp, (list, tuple)) and len(sp) == 2):
            raise InputError(f"{where}: spacing must be [dx, dy] in mm, got {sp!r}")
    try:
        if s.get("frames") is not None and isinstance(s["frames"], str):
            s["frames"] = frame_selection(s["frames"])
        if s.get("spacing") is not None:
            s["spacing"] = [None if v is None else spacing_value(str(v)) for v in s["spacing"]]
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None
    for key in ("shape", "element_size"):
        v = s.get(key)
        if v is not None and not isinstance(v, (list, tuple)):
            s[key] = [v]
    try:
        # the reader's checks (the file's calibration, sampling rate, IQ) go with the orientation check, as on
        # the command line
        reader = dict(reader_kwargs(s), check_orientation=not s.get("no_orientation_check", False))
        reg = registration_kwargs(s)
    except (InputError, TypeError) as exc:
        raise InputError(f"{where}: {exc}") from None
    if s["task"] not in ("register", "track"):
        raise InputError(f"{where}: task must be 'register' or 'track', got {s['task']!r}")
    if s["mode"] not in ("accumulate", "direct") or s["grid"] not in ("current", "reference") \
            or s["init"] not in ("previous", "blockmatch"):
        raise InputError(f"{where}: mode/grid/init must be accumulate|direct, current|reference, "
                         f"previous|blockmatch; got {s['mode']!r}, {s['grid']!r}, {s['init']!r}")
    pairs = s["pairs"]
    if not (isinstance(pairs, (list, tuple)) and pairs and all(
            isinstance(p, (list, tuple)) and len(p) == 2 and all(isinstance(i, int) and i >= 0 for i in p)
            for p in pairs)):
        raise InputError(f"{where}: pairs must be a list of [reference, moving] frame indices >= 0, got {pairs!r}")
    return reader, reg
