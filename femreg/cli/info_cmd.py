"""``femreg info FILE``: what is in an RF data file (format, frames, shape, dtype as stored, spacing, values,
variables, header), with or without spacing, and what it would need to be registered.

Exit codes: 0 described, ready to register; 1 described, but it needs something first (no spacing in the file,
frames that look transposed or a spacing that looks swapped: the ``needs`` lines); 2 the file cannot be read."""
from __future__ import annotations

import functools
import json
import os
from pathlib import Path

import numpy as np

from ..errors import FileFormatError, InputError, SpacingUnknownError
from ._common import add_reader_args, array_headers, frames_from_args


def add_parser(subparsers):
    p = subparsers.add_parser(
        "info", help="describe an RF data file (format, frames, shape, spacing, header)",
        description="Read FILE (npy, npz, mat v5/v7.3, mhd/mha, raw, Clarius raw exports (told by their header), "
                    "Ultrasonix .rf, UFF, HDF5, DICOM, or a directory of per-frame files) and print its format, "
                    "number of frames, frame shape (axial x "
                    "lateral), sample type as stored, spacing, value range, variables and header fields, and what is "
                    "missing to register it (spacing; frames that look transposed or a spacing that looks "
                    "swapped, from the RF carrier: femreg.orientation).")
    p.add_argument("file", help="data file or directory of frame files")
    add_reader_args(p)
    p.add_argument("--json", action="store_true", help="print a JSON object instead of text")
    p.add_argument("--volume", action="store_true",
                   help="read FILE as RF volume(s): a 3D array is one volume (axial, lateral, elevational), a 4D "
                        "one a sequence (frames first; MATLAB: last); spacing (dx, dy, dz) from the file.  Files "
                        "that can only be volumes (4D data, three spacing values) are read so without it")
    p.set_defaults(func=run)
    return p


#: Metadata printed with the lines above (or, for a DICOM region, by its ``crop`` line), not again.
_SHOWN = ("origin_given", "overlay_fraction", "spacing_source", "origin_source", "frame_rate", "frame_rate_source", "region",
          "header_spacing")


def _plain(v):
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v if isinstance(v, (int, float, str, bool, type(None))) else str(v)


def _variables(path: Path) -> dict:
    """{name: "shape dtype"} of the arrays in an .npz or .mat file, read from headers only ({} otherwise)."""
    return {k: f"{'x'.join(map(str, shape)) or 'scalar'} {dtype}" for k, (shape, dtype) in array_headers(path).items()}


def _what_is_missing(exc: InputError, path: Path, args):
    """(the need in words as a function of ``beam`` -- convex / sector frames, whose lateral value is the angle
    pitch --, reader kwargs to read the file for its description anyway) from a reader error."""
    if isinstance(exc, SpacingUnknownError):
        given = list(getattr(args, "spacing", None) or [None, None])
        need = ("no spacing found: pass --spacing DX DY (axial, lateral mm)" if given == [None, None] else
                "spacing incomplete: pass both values, --spacing DX DY (axial, lateral mm)")
        def need_for(beam=False, suggestion=None):
            if beam and given[0] is not None and given[1] is None:
                return None         # --spacing DX auto: a convex / phased array's rays are --angle-pitch apart
            s = suggestion or exc.suggestion
            return need + (f"; {s.text(beam=beam)}" if s else "")
        return need_for, {"spacing": [v if v is not None else 1.0 for v in given]}
    return (lambda beam=False: str(exc)), {}


def _iq_spacing_suggestion(iq, exc, args):
    """The header's spacing suggestion for IQ frames read without a spacing, its axial value the IQ samples' where
    the IQ phases between frames 0 and 1 show the IQ decimated after sampling at the header's rate
    (:func:`femreg.orientation.iq_decimation_from_phases`, at the demodulation frequency given or the file
    states); None where the suggestion stands or nothing can tell."""
    import dataclasses

    from ..io.checks import header_frequencies
    from ..orientation import iq_decimation_from_phases

    sug = getattr(exc, "suggestion", None)
    try:
        dx_fs = float(sug.dx)
    except (AttributeError, TypeError, ValueError):
        return None                 # no suggestion, or no sampling rate in it
    known = header_frequencies(iq.metadata)
    f = getattr(args, "modulation_frequency", None)
    f_words = f"{f:g} MHz, the frequency given" if f is not None else ""
    if f is None and "demod_mhz" in known:
        f, f_words = known["demod_mhz"][0], f"{known['demod_mhz'][0]:g} MHz, the demodulation frequency the file states"
    if f is None or iq.n_frames < 2 or not np.iscomplexobj(iq.frames):
        return None
    c = getattr(args, "sound_speed", None) or known.get("sound_speed", (1540.0,))[0]
    try:
        q = iq_decimation_from_phases(iq.frames[0], iq.frames[1], dx_fs, float(f), float(c))
    except (InputError, ValueError):
        return None
    if q is None or q == 1:
        return None
    rate = sug.why_x[len("axial "):] if sug.why_x.startswith("axial ") else sug.why_x
    rate = rate.split(", the step of IQ")[0]        # the caveat the phases settle
    return dataclasses.replace(sug, dx=f"{q * dx_fs:.5g}", why_x=(
        f"axial {q} x {rate}: the IQ phases between frames 0 and 1 fit {f_words}, at {q} times that step (IQ "
        f"decimated {q}x after sampling)"))


def describe(fr, *, spacing_known: bool = True) -> dict:
    a = fr.frames
    meta = dict(fr.metadata)
    stored = meta.pop("stored_dtype", None) or dict(meta.get("file_metadata") or {}).get("stored_dtype")
    if isinstance(meta.get("file_metadata"), dict):
        meta["file_metadata"] = {k: v for k, v in meta["file_metadata"].items() if k != "stored_dtype"}
    iq = np.iscomplexobj(a)
    v = np.abs(a) if iq else a               # IQ: the values described are |IQ|
    out = {
        "file": str(fr.source), "format": meta.pop("format", ""), "frames": fr.n_frames,
        "shape": list(fr.shape), "dtype": stored or str(a.dtype), "dtype_in_memory": str(a.dtype),
        "spacing_mm": list(fr.spacing) if spacing_known else None, "origin_mm": list(fr.origin),
        "extent_mm": [fr.shape[0] * fr.spacing[0], fr.shape[1] * fr.spacing[1]] if spacing_known else None,
        "min": float(v.min()), "max": float(v.max()), "mean": float(v.mean()), "std": float(v.std()),
        "metadata": _plain(meta),
    }
    if a.ndim == 3 and a.shape[0] >= 2:      # frames written twice: what track and elastogram will say
        from ..image import leading_repeats, repeated_frames, repeats_listed

        rep = repeated_frames(a)
        if rep:
            shown, last = repeats_listed(rep), leading_repeats(rep)
            verb = "repeats" if len(rep) == 1 else "repeat"
            head = f"{len(rep)} of {fr.n_frames} frames {verb} the one before (identical samples; frames {shown})"
            if len(rep) == fr.n_frames - 1:
                out["repeats"] = f"{head}: every frame the same, nothing to register"
            elif last:
                out["repeats"] = (f"{head}: track cannot start on a repeat of frame 0, start it at frame {last} "
                                  f"(--frames {last}:)")
            else:
                out["repeats"] = f"{head}: track keeps the field of the one before, elastogram names them"
    if iq:      # the RF checks need the carrier, which needs the modulation frequency
        out.update(values_of="|IQ|", needs=[])
        return out
    if spacing_known:
        from ..orientation import diagnose, frequency_note

        rep = diagnose(a[0], fr.spacing, whole_frame=True)     # a file's frames are whole: their size counts
        out["rf_check"] = "" if rep.problem else "; ".join(
            t for t in (_rf_line(rep, a[0], fr.spacing, fr.origin),
                        frequency_note(rep.frequency_mhz) if rep.has_carrier else "") if t)
        out["needs"] = [rep.message] if rep.problem else []
        out["transposed"] = rep.problem == "transposed"
        out["spacing_problem"] = rep.problem if rep.problem in ("swapped", "spacing") else ""
        if "iq" in fr.metadata:      # remodulated IQ: what read_frames checks when registering (spacing, sign, f)
            out["needs"] += _iq_needs(fr)
        if not rep.problem and not rep.has_carrier and "raw" in str(out["format"]):
            out["needs"] += _raw_shape_hint(a[0])
        if not rep.problem and not rep.has_carrier and fr.n_frames >= 2:
            from ..echo import fan_region, find_fill

            fill = find_fill(np.asarray(a[0], float), np.asarray(a[-1], float), fr.spacing, fr.origin)
            if fill is not None:        # what register, track and elastogram leave out: the fan is kept whole
                out["fill"] = (f"{fan_region(fill).excluded}; register, track and elastogram: the whole fan "
                               f"(femreg.echo.fan_region)")
        if fr.n_frames < 2:
            out["note"] = "one frame: register it against a second file (femreg register REF MOV)"
    else:
        from ..orientation import CARRIER_RATIO, NO_CARRIER_RATIO, axial_carrier_ratio, carrier_ratio

        c0 = axial_carrier_ratio(a[0])       # the carrier needs no spacing
        out["needs"] = _raw_shape_hint(a[0]) if "raw" in str(out["format"]) and not c0 < CARRIER_RATIO else []
        if not out["needs"] and "raw" not in str(out["format"]) and c0 > NO_CARRIER_RATIO:
            # lines first: said now, not only once a spacing is given (the carrier's axis needs none)
            if carrier_ratio(np.asarray(a[0], float)[::max(1, a.shape[1] // 1024)].T) < CARRIER_RATIO:
                out["needs"] = ["the frames look transposed: the RF carrier runs along axis 1 (lines x samples): "
                                "pass --transpose (and --spacing DX DY as axial, lateral)"]
                out["transposed"] = True
    return out


def _probe_need(info) -> str:
    """The ``--geometry`` a convex or phased array's frames need, from the header fields ("" for none)."""
    from ..io.checks import geometry_hint, header_axes, header_fields

    meta = info.get("metadata")
    hint = geometry_hint(header_fields(meta), header_axes(meta), (info.get("shape") or [None, None])[1])
    return (f"frames along the rays of a curved or phased array: register with the probe geometry; {hint} "
            "(--geometry linear if the frames are on a Cartesian grid already)") if hint else ""


def _spacing_conflict(info, args, fr=None) -> list:
    """The refusal of ``register`` / ``track`` for a ``--spacing`` that contradicts the file's calibration (a
    DICOM ultrasound region's), and of frames whose axial spacing contradicts the file's RF sampling rate or
    transmit frequency (:func:`femreg.orientation.check_sampling`, on ``fr``, the frames as read), as a list of
    needs ([] when they agree or the file states none); the latter's notes go to ``info["note"]``."""
    from ..io.frames import Frames
    from ..io.readers import _check_given_spacing
    from ..orientation import check_sampling

    meta = dict(info.get("metadata") or {}, format=info.get("format", ""))
    if info.get("spacing_mm") is None or getattr(args, "spacing_stand_in", False):
        return []           # no spacing, or a stand-in
    given = getattr(args, "spacing", None)
    if fr is None:          # no samples: only the spacing is held against the header
        fr = Frames(frames=np.zeros((1, 2, 2)), spacing=tuple(info["spacing_mm"]), metadata=meta,
                    source=info["file"])
    try:
        if given is not None and meta.get("header_spacing") is not None:
            _check_given_spacing(fr, given)
        notes = [] if info.get("rf_check") == "" else check_sampling(   # "": refused by the orientation checks
            fr, given, sound_speed=getattr(args, "sound_speed", None), where=f"{info['file']}: ")
    except InputError as exc:
        return [str(exc)]
    if notes:
        info["note"] = "; ".join(n for n in (info.get("note"), *notes) if n)
    return []


def _origin_note(info, args) -> str:
    """A note when the header states a start depth (``t0``, ``start_depth``) that the frames' origin, 0 as read,
    does not carry: a linear array's depths are labelled from the first sample unless ``--origin`` is given; with
    ``--geometry convex|sector`` the commands take it as the first range, which the rays' geometry needs ("" when
    the header states none)."""
    from ..io.checks import unapplied_start_depth

    depth, why = unapplied_start_depth(info.get("metadata"), info["origin_mm"], getattr(args, "sound_speed", None))
    if depth is None:
        return ""
    return (f"the first sample is read at depth 0, but the header states {depth:.4g} mm ({why}): for a linear "
            f"array pass --origin {depth:.4g} 0 to label depths from it; with --geometry convex or sector it is "
            "applied as the first range (the rays' geometry depends on it; --origin R0 0 overrides)")


def _iq_needs(fr) -> list:
    """The problems :func:`femreg.io.read_frames` refuses remodulated IQ frames for (exchanged spacings, the
    other sign convention, another demodulation frequency), as a list of needs ([] when they pass)."""
    from ..orientation import OrientationError, check_iq_sign, check_remodulated

    try:
        check_remodulated(fr)
        if fr.n_frames >= 2:
            check_iq_sign(fr.frames[0], fr.frames[1], fr.spacing, fr.metadata["iq"], metadata=fr.metadata)
    except OrientationError as exc:
        return [str(exc)]
    return []


def _raw_shape_hint(frame) -> list:
    """The ``--shape`` advice of :func:`femreg.orientation.exchanged_shape` as a list of needs."""
    from ..orientation import exchanged_shape

    msg = exchanged_shape(frame)
    return [msg] if msg else []


#: Top parts of the depth (fractions) read for a carrier where the whole depth shows none (:func:`_rf_line`).
TOP_PARTS = (0.75, 0.5, 0.25)


def _rf_line(rep, frame, spacing, origin) -> str:
    """The ``RF`` line of ``femreg info``: ``rep.summary()``, except for zero-mean frames whose whole depth shows no
    carrier but whose top part does (:data:`TOP_PARTS`; :data:`femreg.orientation.CARRIER_RATIO`): RF whose deep
    samples are broadband noise (e.g. lifted by a time-gain compensation), said so, not "envelope or B-mode"."""
    from ..echo import rf_like
    from ..orientation import CARRIER_RATIO, axial_carrier_ratio, diagnose

    if rep.problem or rep.has_carrier or not rf_like(frame):
        return rep.summary()
    n = frame.shape[0]
    for part in TOP_PARTS:
        k = int(part * n)
        if axial_carrier_ratio(frame[:k]) < CARRIER_RATIO:
            top = diagnose(frame[:k], spacing)
            if top.problem or not top.has_carrier:
                break
            below = axial_carrier_ratio(frame[k:])
            depth = origin[0] + (k - 0.5) * spacing[0]
            return (f"above {depth:.1f} mm: {top.summary()}; below it the samples are broadband (low/centre band "
                    f"power {below:.2g}, the whole depth {rep.carrier[0]:.2g}): receiver noise, e.g. lifted by a "
                    "time-gain compensation (registration leaves out what does not match)")
    return rep.summary()


def describe_volumes(path: Path, args) -> dict:
    """The description of a volume file (:func:`femreg.io.read_volumes`); spacing from the file."""
    from ..io import read_volumes

    kw = dict(variable=getattr(args, "variable", None), frames=getattr(args, "frames", None))
    given = getattr(args, "spacing", None)
    if given is not None and len(given) != 3:
        raise InputError(f"{path}: volumes take --spacing DX DY DZ (axial, lateral, elevational, mm), got "
                         f"{len(given)} values")
    needs = []
    try:
        vol = read_volumes(path, spacing=given, **kw)
        known = True
    except InputError as exc:
        if not isinstance(exc, SpacingUnknownError):
            raise
        vol = read_volumes(path, spacing=(1.0, 1.0, 1.0), check_sampling=False, **kw)
        known = False
        sug = getattr(exc, "suggestion", None)
        needs.append("no spacing found: volumes need spacing (dx, dy, dz) in mm stored with them (npz key "
                     "'spacing', MAT variable 'spacing', MetaImage ElementSpacing) or --spacing DX DY DZ"
                     + (f"; {sug.text()}" if sug is not None else ""))
    a = vol.frames
    meta = dict(vol.metadata)
    stored = meta.pop("stored_dtype", None)
    out = {
        "file": str(vol.source), "format": meta.pop("format", ""), "kind": "volume", "frames": vol.n_frames,
        "shape": list(vol.shape), "dtype": stored or str(a.dtype), "dtype_in_memory": str(a.dtype),
        "spacing_mm": list(vol.spacing) if known else None, "origin_mm": list(vol.origin),
        "extent_mm": [n * d for n, d in zip(vol.shape, vol.spacing)] if known else None,
        "min": float(a.min()), "max": float(a.max()), "mean": float(a.mean()), "std": float(a.std()),
        "metadata": _plain(meta), "needs": needs,
    }
    if known:
        from ..orientation import diagnose

        plane = a[0][:, :, a.shape[3] // 2]                # the central axial-lateral plane
        rep = diagnose(plane, vol.spacing[:2], elevational=vol.spacing[2])
        out["rf_check"] = "" if rep.problem else _rf_line(rep, plane, vol.spacing[:2], vol.origin[:2])
        out["needs"] += [rep.message] if rep.problem else []
        if vol.n_frames < 2:
            out["note"] = "one volume: register it against a second file"
    return out


def _no_spacing_line(needs) -> str:
    """The ``spacing`` line of a file read without one: whether its header fields suggest one (needs lines)."""
    if any("its fields suggest --spacing" in n for n in needs):
        return "spacing   not stored as such; the header fields suggest one (needs, below)"
    return "spacing   none in the file"


def _print_volumes(info) -> None:
    print(f"file      {info['file']}")
    print(f"format    {info['format']} (volumes)")
    print(f"volumes   {info['frames']}")
    n = info["shape"]
    print(f"shape     {n[0]} axial x {n[1]} lateral x {n[2]} elevational")
    print(f"dtype     {info['dtype']} as stored" + (f" (read as {info['dtype_in_memory']})"
                                                    if info["dtype_in_memory"] != info["dtype"] else ""))
    if info["spacing_mm"] is not None:
        s, o, e = info["spacing_mm"], info["origin_mm"], info["extent_mm"]
        print(f"spacing   {s[0]:g} mm axial, {s[1]:g} mm lateral, {s[2]:g} mm elevational")
        print(f"origin    {o[0]:g}, {o[1]:g}, {o[2]:g} mm")
        print(f"extent    {e[0]:g} mm x {e[1]:g} mm x {e[2]:g} mm")
    else:
        print(_no_spacing_line(info["needs"]))
    print(f"values    {info.get('values_of', '')}{' ' if info.get('values_of') else ''}min {info['min']:.6g}, "
          f"max {info['max']:.6g}, mean {info['mean']:.6g}, "
          f"std {info['std']:.6g}")
    if info.get("rf_check"):
        print(f"RF        {info['rf_check']} (central plane)")
    for name, desc in info.get("variables", {}).items():
        print(f"array     {name:16s} {desc}")
    if info.get("note"):
        print(f"note      {info['note']}")
    for need in info["needs"]:
        print(f"needs     {need}")
    if not info["needs"]:
        print("needs     nothing: ready to register")


def _run_volumes(path: Path, args) -> int:
    info = describe_volumes(path, args)
    variables = _variables(path) if path.is_file() else {}
    if variables:
        info["variables"] = variables
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        _print_volumes(info)
    return 1 if info["needs"] else 0


def run(args) -> int:
    path = Path(os.fspath(args.file))
    spacing_need = None             # the missing spacing's need, said again for convex / sector frames
    from ._common import volumes_only

    if getattr(args, "volume", False) or volumes_only(path):   # as register and track read it
        return _run_volumes(path, args)
    fr = None
    try:
        fr = frames_from_args(args, allow_sector=True, check_shape=False)
        info = describe(fr)
    except FileFormatError as exc:    # a file that can only hold volumes names the volume reader
        if "read_volumes" not in str(exc):
            raise
        try:
            return _run_volumes(path, args)
        except ValueError:
            raise exc from None
    except InputError as exc:
        need_for, retry = _what_is_missing(exc, path, args)
        need = need_for()
        info = None
        iq = getattr(exc, "iq_frames", None)
        if iq is None and retry:
            # described with a stand-in spacing; IQ data are described as stored (a remodulation needs the spacing)
            saved = args.spacing, getattr(args, "modulation_frequency", None)
            args.spacing, args.modulation_frequency = retry["spacing"], None
            args.spacing_stand_in = True        # not typed: no note that it differs from the file's fields
            try:
                info = describe(frames_from_args(args, allow_sector=True, check_shape=False), spacing_known=False)
            except InputError as again:
                iq = getattr(again, "iq_frames", None)
                if iq is None:
                    raise
            finally:
                args.spacing, args.modulation_frequency = saved
                args.spacing_stand_in = False
        if iq is not None:
            info = describe(iq, spacing_known=not retry)
            better = _iq_spacing_suggestion(iq, exc, args) if retry else None
            if better is not None:
                need_for = functools.partial(need_for, suggestion=better)
                need = need_for()
            if getattr(args, "modulation_frequency", None) is None:
                from ..io.checks import iq_frequency_hint

                hint = iq_frequency_hint(dict(iq.metadata).get("fields") or {})
                info["needs"].append("IQ data (complex samples): pass --iq-frequency MHZ, the demodulation frequency, "
                                     "to remodulate them to RF" + (f"; {hint}" if hint else ""))
            if not retry:
                need = None
        if info is None:            # unreadable as given (raw without --shape, no such variable, ...): exit 2
            raise
        if need is None:
            need = info["needs"].pop(0)
        else:
            spacing_need = need_for
        info["needs"] = [need] + info.get("needs", [])
    variables = _variables(path) if path.is_file() else {}
    if variables:
        info["variables"] = variables
    if info.get("spacing_problem") and args.spacing is None and info["needs"]:
        # the spacing judged is the file's: say so, as register does
        from ..orientation import OrientationError
        from . import _header_spacing_note, file_spacing_wording

        note = _header_spacing_note(args, OrientationError("", problem=info["spacing_problem"]))
        info["needs"][0] = file_spacing_wording(info["needs"][0]) + note
    info.pop("spacing_problem", None)
    info["needs"] += _spacing_conflict(info, args, fr)
    start = _origin_note(info, args)
    if start:
        info["note"] = "; ".join(n for n in (info.get("note"), start) if n)
    probe = _probe_need(info)
    if probe:
        # a convex / phased array's lateral spacing is its angle pitch, not a line pitch the file should state
        if spacing_need is not None:
            beam_need = spacing_need(beam=True)
            if beam_need is None:
                info["needs"].pop(0)
                info["range_step_mm"] = float(args.spacing[0])
            else:
                info["needs"][0] = beam_need
        info["needs"].append(probe)
    # 0: ready to register; 1: described, but it needs something first (printed); 2 (raised): unreadable
    rc = 1 if info["needs"] else 0
    if args.json:
        print(json.dumps(info, indent=2))
        return rc
    print(f"file      {info['file']}")
    print(f"format    {info['format']}")
    print(f"frames    {info['frames']}")
    if info.get("transposed"):         # axis 0 holds the lines: calling it axial would contradict the needs line
        print(f"shape     {info['shape'][0]} x {info['shape'][1]} as stored: lines x samples, "
              f"{info['shape'][1]} axial x {info['shape'][0]} lateral with --transpose")
    else:
        print(f"shape     {info['shape'][0]} axial x {info['shape'][1]} lateral")
    print(f"dtype     {info['dtype']} as stored" + (f" (read as {info['dtype_in_memory']})"
                                                    if info["dtype_in_memory"] != info["dtype"] else ""))
    meta = info.get("metadata", {})
    if info["spacing_mm"] is not None:
        src = meta.get("spacing_source") or ""
        if meta.get("header_spacing") is not None and not np.allclose(info["spacing_mm"], meta["header_spacing"]):
            src = f"given; the file states {', '.join(f'{v:g}' for v in meta['header_spacing'])} mm, {src}"
        src = f" ({src})" if src else ""
        print(f"spacing   {info['spacing_mm'][0]:g} mm axial, {info['spacing_mm'][1]:g} mm lateral{src}")
        src = f" ({meta['origin_source']})" if meta.get("origin_source") else ""
        print(f"origin    {info['origin_mm'][0]:g}, {info['origin_mm'][1]:g} mm{src}")
        print(f"extent    {info['extent_mm'][0]:g} mm x {info['extent_mm'][1]:g} mm"
              + (" as read without --transpose" if info.get("transposed") else ""))
    elif info.get("range_step_mm") is not None:
        print(f"spacing   {info['range_step_mm']:g} mm range step (given); the rays are --angle-pitch apart")
    else:
        print(_no_spacing_line(info["needs"]))
    print(f"values    {info.get('values_of', '')}{' ' if info.get('values_of') else ''}min {info['min']:.6g}, "
          f"max {info['max']:.6g}, mean {info['mean']:.6g}, "
          f"std {info['std']:.6g}")
    if info.get("rf_check"):
        print(f"RF        {info['rf_check']}")
    if info.get("fill"):
        print(f"fill      {info['fill']}")
    for name, desc in info.get("variables", {}).items():
        print(f"array     {name:16s} {desc}")
    if info.get("repeats"):
        print(f"repeats   {info['repeats']}")
    if isinstance(meta.get("frame_rate"), (int, float)):
        src = f" ({meta['frame_rate_source']})" if meta.get("frame_rate_source") else ""
        print(f"frame rate {meta['frame_rate']:.4g} Hz{src}")
    for key, val in meta.items():
        if (key == "dtype" and str(val) == info["dtype"]) or key in _SHOWN:
            continue                          # printed above already (sample type, origin, spacing, frame rate)
        if val is None or (isinstance(val, (list, tuple, dict, str)) and len(val) == 0):
            continue                          # nothing to say (e.g. no result file set aside in a folder)
        if key == "axes" and isinstance(val, dict):       # evenly spaced vectors (femreg.io.checks.axis_fields)
            print("axes:")
            for k, v in val.items():
                print(f"  {k:24s} {v['n']} values from {v['first']:.6g}, step {v['step']:.6g}")
        elif isinstance(val, dict):
            print(f"{key}:")
            for k, v in val.items():
                print(f"  {k:24s} {v}")
        elif isinstance(val, list) and len(val) > 12:
            print(f"{key:9s} {val[:6]} ... ({len(val)} items)")
        else:
            print(f"{key:9s} {val}")
    if info.get("note"):
        print(f"note      {info['note']}")
    for need in info["needs"]:
        print(f"needs     {need}")
    if not info["needs"]:
        print("needs     nothing: ready to register")
    return rc
