"""Checks every reader and writer of RF frames shares: file-format errors naming the file, spacing, origin, frame
selection, sample types, and the validated fields of a :class:`femreg.io.Frames` (:func:`validate_frames`).
The lowest module of :mod:`femreg.io`: the format modules (MATLAB, MetaImage, Ultrasonix) build on it and return
those fields; :mod:`femreg.io.readers` turns them into :class:`~femreg.io.Frames`.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FileFormatError, InputError, SpacingUnknownError, pass_as

__all__ = ["fail", "check_spacing", "check_origin", "merge_spacing", "select_frames", "validate_frames",
           "validate_volumes", "FORMATS", "parse_dtype", "spacing_hint", "spacing_suggestion", "SpacingSuggestion", "geometry_fields", "geometry_hint",
           "axis_fields", "header_axes", "header_fields", "origin_hint",
           "unapplied_start_depth", "AXIS_MAX",
           "iq_frequency_hint", "scalar_fields", "natural_key", "header_frequencies"]

FORMATS = {
    ".npy": "npy", ".npz": "npz", ".mat": "mat", ".mhd": "metaimage", ".mha": "metaimage",
    ".raw": "raw", ".bin": "raw", ".dat": "raw", ".f32": "raw", ".i16": "raw", ".rf": "ultrasonix",
    ".uff": "uff", ".h5": "hdf5", ".hdf5": "hdf5", ".hdf": "hdf5", ".he5": "hdf5",
    ".dcm": "dicom", ".dicom": "dicom",
}
_DTYPES = {"float32": "f4", "float": "f4", "single": "f4", "f4": "f4", "met_float": "f4",
           "float64": "f8", "double": "f8", "f8": "f8", "met_double": "f8",
           "int16": "i2", "short": "i2", "i2": "i2", "met_short": "i2",
           "uint16": "u2", "ushort": "u2", "u2": "u2", "met_ushort": "u2",
           "int8": "i1", "i1": "i1", "met_char": "i1", "uint8": "u1", "u1": "u1", "met_uchar": "u1",
           "int32": "i4", "i4": "i4", "met_int": "i4", "uint32": "u4", "u4": "u4", "met_uint": "u4"}


def parse_dtype(dtype, byte_order=None) -> np.dtype:
    """On-disk sample type from a name (``float32``, ``int16``, ``<f4``, ``MET_SHORT``, ...) and byte order
    (``little``/``big``, ``<``/``>``; default little, or the order given in the dtype string)."""
    order = None
    if dtype is None:
        code = "f4"
    elif isinstance(dtype, np.dtype) or (isinstance(dtype, type) and issubclass(dtype, np.generic)):
        dt = np.dtype(dtype)
        code = dt.str[1:]
        order = dt.byteorder if dt.byteorder in "<>" else None
    else:
        s = str(dtype).strip().lower()
        if s[:1] in "<>=|":
            order = s[0] if s[0] in "<>" else None
            s = s[1:]
        code = _DTYPES.get(s)
        if code is None:
            raise InputError(f"unknown dtype {dtype!r}; use one of float32, float64, int16, uint16, int8, uint8, "
                             "int32, uint32")
    if code not in _DTYPES.values():
        raise InputError(f"unsupported dtype {dtype!r} for RF samples")
    if byte_order is not None:
        bo = {"little": "<", "<": "<", "le": "<", "big": ">", ">": ">", "be": ">"}.get(str(byte_order).lower())
        if bo is None:
            raise InputError(f"byte_order must be 'little' or 'big', got {byte_order!r}")
        if order is not None and order != bo and code[1] != "1":
            raise InputError(f"dtype {dtype!r} and byte_order {byte_order!r} disagree")
        order = bo
    return np.dtype((order or "<") + code)


def natural_key(name: str):
    """Sort key with embedded integers compared as numbers (frame2 < frame10)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def fail(path, problem: str) -> FileFormatError:
    """A :class:`FileFormatError` whose one-line message names the file and the problem."""
    problem = " ".join(str(problem).split())  # one line, whatever the wrapped library said
    return FileFormatError(f"{path}: {problem}")


def check_spacing(value, what: str = "spacing", allow_none: bool = False, n: int = 2):
    """Validate ``n`` spacings in mm (``(dx, dy)``, or ``(dx, dy, dz)`` for volumes): positive finite numbers (or
    None entries if allowed)."""
    if value is None:
        return None
    names = "(dx, dy)" if n == 2 else "(dx, dy, dz)"
    try:
        vals = list(np.asarray(value, dtype=object).ravel())
    except Exception as exc:  # pragma: no cover - np.asarray on odd objects
        raise InputError(f"{what} must be {_num(n)} numbers {names} in mm, got {value!r}") from exc
    if len(vals) != n:
        raise InputError(f"{what} must be {_num(n)} numbers {names} in mm, got {value!r}")
    out = []
    for v in vals:
        if v is None and allow_none:
            out.append(None)
            continue
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise InputError(f"{what} must be {_num(n)} numbers {names} in mm, got {value!r}") from None
        if not (math.isfinite(f) and f > 0):
            raise InputError(f"{what} must be positive and finite (mm), got {value!r}")
        out.append(f)
    return tuple(out)


def _num(n: int) -> str:
    return {2: "two", 3: "three"}.get(n, str(n))


def check_origin(value, path=None, n: int = 2):
    if value is None:
        return (0.0,) * n
    names = "(x0, y0)" if n == 2 else "(x0, y0, z0)"
    try:
        arr = np.asarray(value, dtype=float).ravel()
    except (TypeError, ValueError):
        raise (fail(path, f"origin must be {_num(n)} numbers, got {value!r}") if path
               else InputError(f"origin must be {_num(n)} numbers, got {value!r}")) from None
    if arr.size != n or not np.all(np.isfinite(arr)):
        msg = f"origin must be {_num(n)} finite numbers {names} in mm, got {value!r}"
        raise fail(path, msg) if path else InputError(msg)
    return tuple(float(v) for v in arr)


def merge_spacing(path, file_spacing, user_spacing, *, required_msg: str | None = None, n: int = 2,
                  suggestion: "SpacingSuggestion | None" = None, frame_shape=None):
    """Spacing from the file, overridden component-wise by the user's (None entries keep the file's); where a
    value is still missing, :class:`~femreg.errors.SpacingUnknownError` with ``required_msg`` (why the file has
    none), the header's ``suggestion`` (:func:`spacing_suggestion`) and the reader's ``frame_shape`` (axial,
    lateral samples as stored)."""
    user = check_spacing(user_spacing, allow_none=True, n=n)
    file_sp = list(file_spacing) if file_spacing is not None else [None] * n
    if user is not None:
        file_sp = [u if u is not None else f for u, f in zip(user, file_sp)]
    if any(v is None for v in file_sp):
        axes = ("axial dx", "lateral dy", "elevational dz")
        missing = " and ".join(a for a, v in zip(axes, file_sp) if v is None)
        msg = required_msg or "this format stores no pixel spacing"
        hint = pass_as("spacing=(dx, dy) in mm (CLI: --spacing DX DY)", "--spacing DX DY (mm)") if n == 2 else \
            pass_as("spacing=(dx, dy, dz) in mm (CLI: --spacing DX DY DZ)", "--spacing DX DY DZ (mm)")
        if suggestion is not None:
            msg = f"{msg}; {suggestion.text()}"
        raise SpacingUnknownError(f"{path}: {missing} spacing unknown ({msg}); give {hint}", path=path,
                                  missing=[a for a, v in zip(axes, file_sp) if v is None], suggestion=suggestion,
                                  frame_shape=frame_shape)
    try:
        return check_spacing(file_sp, what="spacing", n=n)
    except InputError as exc:
        raise fail(path, f"bad spacing {tuple(file_sp)} (must be positive, finite, mm)") from exc


def select_frames(path, arr: np.ndarray, frames):
    """Apply a frame selection (int, slice, sequence of ints, or None = all) to an (n, ...) stack."""
    if frames is None:
        return arr
    n = arr.shape[0]
    if isinstance(frames, slice) and isinstance(frames.stop, (int, np.integer)) and (frames.step or 1) > 0 \
            and frames.stop > n:
        # a stop past the end would be cut short silently: the file is shorter than the user thinks
        a = frames.start or 0
        raise InputError(f"{path}: frame selection {a}:{frames.stop} reaches past the last frame (the file has {n}, "
                         f"0 to {n - 1}); {a}: selects every frame from {a} on")
    try:
        if isinstance(frames, slice):
            idx = np.arange(n)[frames]
        else:
            idx = np.atleast_1d(np.asarray(frames))
            if idx.dtype.kind not in "iu" or idx.ndim != 1:
                raise TypeError
    except (TypeError, ValueError):
        raise InputError(f"frames must be an int, a slice or a list of ints, got {frames!r}") from None
    if idx.size == 0:
        shown = (":".join("" if v is None else str(v) for v in (frames.start, frames.stop))
                 + ("" if frames.step is None else f":{frames.step}")) if isinstance(frames, slice) else repr(frames)
        raise InputError(f"{path}: frame selection {shown} selects no frame (the file has {n}, counted from 0: 0 to "
                         f"{n - 1})")
    bad = idx[(idx < -n) | (idx >= n)]
    if bad.size:
        raise InputError(f"{path}: frame index {int(bad[0])} out of range (the file has {n} frame(s), counted from "
                         f"0: 0 to {n - 1})")
    return arr[idx]


def _real_samples(path, arr, allow_complex: bool = False) -> np.ndarray:
    """``arr`` as an array of real numbers (bool, int, float; complex IQ samples where ``allow_complex``), else
    FileFormatError naming the type."""
    arr = np.asarray(arr)
    if arr.dtype.kind == "c" and not allow_complex:
        raise fail(path, f"complex data ({arr.dtype}) is IQ, not RF; remodulate it to RF first "
                         "(femreg.io.iq.remodulate)")
    if arr.dtype.kind not in "biufc":
        raise fail(path, f"data of type {arr.dtype} is not numeric")
    return arr


def _selected_fields(path, arr, spacing, origin, metadata, frames, n: int) -> dict:
    """Shared tail of the frame and volume readers (``arr`` with its frame axis first, ``n`` = 2 or 3 sample
    axes): the frame selection, float32 (float64 kept) in native byte order, finite values; the fields of a
    :class:`femreg.io.Frames` / :class:`femreg.io.Volumes`."""
    arr = select_frames(path, arr, frames)
    metadata = {**(metadata or {}), "stored_dtype": (metadata or {}).get("stored_dtype", arr.dtype.name)}
    if arr.dtype.kind == "c":   # IQ samples, remodulated to RF by read_frames
        out_dtype = np.complex128 if arr.dtype.itemsize == 16 else np.complex64
    else:
        out_dtype = np.float64 if (arr.dtype.kind == "f" and arr.dtype.itemsize == 8) else np.float32
    # native byte order, C-contiguous, own memory
    arr = np.ascontiguousarray(arr, dtype=np.dtype(out_dtype).newbyteorder("="))
    finite = np.isfinite(arr)
    if not finite.all():
        raise fail(path, f"data contains {int(arr.size - np.count_nonzero(finite))} NaN/Inf value(s)")
    return dict(frames=arr, spacing=tuple(float(s) for s in spacing), origin=check_origin(origin, path, n=n),
                metadata=metadata, source=Path(path))


def validate_frames(path, arr, spacing, origin=(0.0, 0.0), metadata=None, frames=None) -> dict:
    """Shared tail of every reader: shape (n, axial, lateral), float dtype, finite values, selection; returns the
    fields of a :class:`femreg.io.Frames` (``Frames(**fields)``).  Complex (IQ) samples are kept complex:
    :func:`femreg.io.read_frames` remodulates them to RF or refuses them."""
    arr = _real_samples(path, arr, allow_complex=True)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        hint = "; a volume sequence is read by femreg.io.read_volumes" if arr.ndim == 4 else ""
        raise fail(path, f"data has {arr.ndim} dimension(s) {arr.shape}; expected 2 (axial, lateral) "
                         f"or 3 (frames, axial, lateral){hint}")
    if min(arr.shape) < 1:
        raise fail(path, f"data is empty, shape {arr.shape}")
    if arr.shape[1] < 2 or arr.shape[2] < 2:
        raise fail(path, f"frame shape {arr.shape[1:]} is degenerate (need at least 2 x 2 samples)")
    return _selected_fields(path, arr, spacing, origin, metadata, frames, n=2)


def validate_volumes(path, arr, spacing, origin=(0.0, 0.0, 0.0), metadata=None, frames=None) -> dict:
    """Shared tail of the volume readers: shape (n, axial, lateral, elevational) (one volume of 3 dimensions gets a
    leading frame axis), float dtype, finite values, selection; returns the fields of a
    :class:`femreg.io.Volumes`."""
    arr = _real_samples(path, arr)
    if arr.ndim == 3:
        arr = arr[None]
    if arr.ndim != 4:
        raise fail(path, f"data has {arr.ndim} dimension(s) {arr.shape}; a volume has 3 (axial, lateral, "
                         "elevational) and a volume sequence 4 (frames, axial, lateral, elevational)")
    if min(arr.shape) < 1:
        raise fail(path, f"data is empty, shape {arr.shape}")
    if min(arr.shape[1:]) < 2:
        raise fail(path, f"volume shape {arr.shape[1:]} is degenerate (need at least 2 samples along each "
                         "axis; a 2D frame or frame sequence is read by femreg.io.read_frames)")
    return _selected_fields(path, arr, spacing, origin, metadata, frames, n=3)


_FS_NAMES = ("fs", "samplingfrequency", "samplingrate", "samplerate", "samplefrequency", "rfsamplingfrequency",
             "fsample", "fsampling", "decimsamplerate")
_PITCH_NAMES = ("pitch", "elementpitch", "linespacing", "linepitch", "lateralspacing", "linedensity")
_C_NAMES = ("c", "c0", "soundspeed", "speedofsound", "sos")
# a matrix array's or swept probe's elevational plane spacing (volumes)
_ELEVATION_NAMES = ("elevationpitch", "elevationalpitch", "elevationspacing", "elevationalspacing",
                    "elevationalstep", "elevationstep", "planepitch", "planespacing", "slicespacing", "zpitch")
_DEMOD_NAMES = ("fdemod", "demodfrequency", "demodulationfrequency", "modulationfrequency", "demodfreq", "fmod",
                "iqfrequency", "fdemodulation", "demodulationfreq")
# the probe's centre / transmit frequency: most IQ exports demodulate at it, so it is a weaker hint
_CENTRE_NAMES = ("f0", "fc", "fcentre", "fcenter", "centrefrequency", "centerfrequency", "centralfrequency",
                 "transmitfrequency", "txfrequency", "probefrequency", "carrierfrequency", "ftx")
_UNITS = ("mhz", "khz", "hz", "mm", "um", "m", "mps", "ms")
# a probe's struct (Verasonics' ``Trans``) names its element pitch ``spacing`` and its centre frequency
# ``frequency``: read as such only there, where they cannot be a sample spacing or another frequency; the pitch only
# with a length unit in its name (``spacingMm``): Verasonics' bare ``Trans.spacing`` is in wavelengths
_PROBE_STRUCTS = ("trans", "transducer", "probe", "xdc")
_PROBE_MEMBERS = {"spacing": "pitch", "frequency": "f0"}
_LENGTH_UNITS = ("mm", "um", "m")


def _key(name: str) -> tuple:
    """(base name, unit suffix or "") of a header field name: ``fs_MHz`` -> ("fs", "mhz"); a probe struct's
    ``Trans/spacingMm`` -> ("pitch", "mm") and ``Trans/frequency`` -> ("f0", "")."""
    parts = str(name).lower().split("/")
    k = "".join(ch for ch in parts[-1] if ch.isalnum())   # a struct's field: its own name
    parent = "".join(ch for ch in parts[-2] if ch.isalnum()) if len(parts) > 1 else ""
    members = _PROBE_MEMBERS if parent in _PROBE_STRUCTS else {}
    for u in ("",) + _UNITS:
        if u and not k.endswith(u):
            continue
        base = k[:len(k) - len(u)]
        if base in members and (members[base] != "pitch" or u in _LENGTH_UNITS):
            return members[base], u
        if u and base in (_FS_NAMES + _PITCH_NAMES + _C_NAMES + _DEMOD_NAMES + _CENTRE_NAMES + _ELEVATION_NAMES):
            return base, u
    return k, ""


def _hz(value: float, unit: str) -> float:
    """A header frequency in Hz: unit from the name's suffix ("mhz", "khz", "hz"), else from the magnitude (a value
    above 1e4 is in Hz, else in MHz)."""
    return value * {"mhz": 1e6, "khz": 1e3, "hz": 1.0}.get(unit, 1.0 if value > 1e4 else 1e6)


@dataclass(frozen=True)
class SpacingSuggestion:
    """The spacing a file's header fields imply (:func:`spacing_suggestion`): ``dx``, ``dy`` as CLI words (a number
    in mm, or "DX" / "DY" where the file holds nothing for it, "auto" for a curved array's lateral), each with its
    reason.  A hint only: readers never apply it."""

    dx: str
    dy: str
    why_x: str
    why_y: str
    dz: str | None = None           # volumes: the elevational plane spacing ("DZ" where the file holds none)
    why_z: str = ""

    def text(self, beam: bool = False) -> str:
        """The hint in words; ``beam``: for convex / sector frames, whose lateral value is not used (an unknown
        line pitch becomes ``auto``)."""
        dy, why_y = (("auto", "auto: the rays are --angle-pitch apart") if beam and self.dy == "DY"
                     else (self.dy, self.why_y))
        dz, why_z = ("", "") if self.dz is None else (f" {self.dz}", f"; {self.why_z}")
        return (f"its fields suggest --spacing {self.dx} {dy}{dz} ({self.why_x}; {why_y}{why_z}): check them "
                "against the scanner's settings")


_NO_PITCH = ("DY, the lateral line pitch in mm, is not in the file (for a linear array usually the probe's element "
             "pitch; a convex or phased array takes --geometry convex / sector and --spacing DX auto)")


def spacing_suggestion(fields: dict, volume: bool = False, iq: bool = False) -> "SpacingSuggestion | None":
    """The ``--spacing DX DY`` a file's header fields imply (:class:`SpacingSuggestion`), or None when they hold
    neither a sampling frequency nor a pitch (with one of them, the other value is named as missing).  ``dx = c / (2 fs)``
    (pulse-echo), ``c`` 1540 m/s unless a field gives it; units from the name's suffix (``fs_MHz``, ``pitch_mm``) or else from the magnitude (a sampling frequency above 1e4 is in Hz, a pitch
    below 0.005 in metres).  A hint only: readers never apply it.  ``volume``: also the elevational plane
    spacing ``DZ`` (``elevation_pitch``, ``elevational_spacing``, ...; :data:`_ELEVATION_NAMES`).  ``iq``: the
    frames are IQ, often decimated after sampling, so ``c / (2 fs)`` may be a whole fraction of their step: said
    in the reason (``femreg info`` reads the decimation from the IQ phases)."""
    found = {}
    for name, value in fields.items():
        try:
            v = float(np.asarray(value).ravel()[0]) if np.asarray(value).size == 1 else None
        except (TypeError, ValueError):
            v = None
        if v is None or not (math.isfinite(v) and v > 0):
            continue
        base, unit = _key(name)
        for kind, names in (("fs", _FS_NAMES), ("pitch", _PITCH_NAMES), ("c", _C_NAMES),
                            ("elevation", _ELEVATION_NAMES)):
            if base in names and kind not in found:
                found[kind] = (name, v, unit)
    if "fs" not in found and "pitch" not in found:
        return None
    c_name, c, _ = found.get("c", ("", 1540.0, ""))
    if "fs" in found:
        fs_name, fs, fu = found["fs"]
        fs_hz = _hz(fs, fu)
        dx = f"{c * 1e3 / (2.0 * fs_hz):.4g}"
        why_x = (f"axial c / (2 fs) with {fs_name} = {fs:g} read as {fs_hz / 1e6:g} MHz and c = {c:g} m/s"
                 f"{'' if c_name else ' assumed'}")
        if iq:
            why_x += (", the step of IQ sampled at that rate; IQ decimated q times after sampling has q times it "
                      "(femreg info FILE reads q from the IQ phases between frames 0 and 1)")
    else:
        dx, why_x = "DX", "DX, the axial sample step c / (2 fs) in mm, is not in the file (no sampling frequency)"
    if "pitch" in found:
        p_name, p, pu = found["pitch"]
        p_mm = _pitch_mm(p, pu)
        dy, why_y = f"{p_mm:.4g}", f"lateral {p_name} = {p:g} read as {p_mm:g} mm"
    elif geometry_fields(fields):
        dy, why_y = "auto", ("auto: the lateral value is not used for a convex or phased array, whose rays are "
                             "--angle-pitch apart")
    else:
        dy, why_y = "DY", _NO_PITCH
    if not volume:
        return SpacingSuggestion(dx, dy, why_x, why_y)
    if "elevation" in found:
        e_name, e, eu = found["elevation"]
        e_mm = _pitch_mm(e, eu)
        dz, why_z = f"{e_mm:.4g}", f"elevational {e_name} = {e:g} read as {e_mm:g} mm"
    else:
        dz, why_z = "DZ", "DZ, the elevational plane spacing in mm, is not in the file"
    return SpacingSuggestion(dx, dy, why_x, why_y, dz, why_z)


def _pitch_mm(value: float, unit: str) -> float:
    """A header pitch in mm: unit from the name's suffix ("mm", "um", "m"), else from the magnitude (below 0.005:
    metres)."""
    return value * {"mm": 1.0, "um": 1e-3, "m": 1e3}.get(unit, 1e3 if value < 0.005 else 1.0)


def spacing_hint(fields: dict) -> str:
    """:func:`spacing_suggestion` in words, "" without one."""
    sug = spacing_suggestion(fields)
    return sug.text() if sug is not None else ""


# convex / phased-array header fields (last path component, lower-case alphanumerics, unit suffix removed)
_RADIUS_NAMES = ("radius", "convexradius", "proberadius", "arrayradius", "curvatureradius", "radiusofcurvature",
                 "roc", "apexdistance", "transducerradius")
_ANGLE_PITCH_NAMES = ("anglepitch", "angularpitch", "dtheta", "rayangle", "raypitch", "lineangle",
                      "angleincrement", "angularstep", "beamangle", "beamanglepitch", "lineanglepitch")
# vectors of the rays' angles, one per line (e.g. a scan's ``theta``); a plane-wave sequence's steering ``angles``
# has as many values as transmits, not lines, and is told apart by its length
_ANGLE_VECTOR_NAMES = ("theta", "thetas", "angles", "rayangles", "beamangles", "lineangles", "scantheta",
                       "scanangles", "azimuth", "azimuthangles", "steeringangles", "sectorangles")


# an angle-pitch field is also named stem + step word (``line_angle_step``, ``ray_angle_increment``); a bare
# ``angle_step`` / ``theta_step`` is left out: a plane-wave sequence's steering step on a linear array reads so
_ANGLE_STEMS = ("lineangle", "rayangle", "beamangle", "scanangle", "scanlineangle")
_STEP_WORDS = ("pitch", "step", "increment", "inc", "spacing", "delta", "interval", "separation")


def _is_angle_pitch(base: str) -> bool:
    """True for a header field's base name (:func:`_name_unit`) that names the angle between neighbouring rays."""
    if base in _ANGLE_PITCH_NAMES:
        return True
    for stem in _ANGLE_STEMS:
        if base.startswith(stem) and base[len(stem):] in _STEP_WORDS:
            return True
        if base in (f"d{stem}", f"delta{stem}"):
            return True
    return False


def _name_unit(name: str, units, bases) -> tuple:
    """(base, unit) of a header field's name (last path component, lower-case alphanumerics): the unit suffix among
    ``units`` removed where the rest is one of ``bases``; else (the whole name, "")."""
    k = "".join(ch for ch in str(name).split("/")[-1].lower() if ch.isalnum())
    for u in units:
        if k.endswith(u) and (k[:-len(u)] in bases or _is_angle_pitch(k[:-len(u)])):
            return k[:-len(u)], u
    return k, ""


def _geometry_key(name: str) -> tuple:
    """(base, unit) of a header field for the probe geometry: ``probe/angle_pitch_deg`` -> ("anglepitch", "deg")."""
    return _name_unit(name, ("deg", "rad", "mm", "m"), _RADIUS_NAMES + _ANGLE_PITCH_NAMES + _ANGLE_VECTOR_NAMES)


def geometry_fields(fields: dict, axes: dict | None = None, n_lines: int | None = None) -> dict:
    """The probe geometry a file's header fields state: ``{"radius_mm": R, "angle_pitch_deg": A, "names": (...)}``
    with the entries found (a convex radius in mm, the angle between rays in degrees; a radius alone where the file
    holds no angle, still a convex array), or {}.  Units from the
    name's suffix (``_mm``, ``_m``, ``_deg``, ``_rad``) or else the magnitude (a radius below 0.5 in metres, an
    angle pitch below 0.05 in radians).  ``axes`` (:func:`axis_fields`): an evenly spaced vector of the rays'
    angles (``theta``, ``angles``, ...) with exactly ``n_lines`` values gives the angle pitch too (a vector of
    another length, such as a plane-wave sequence's steering angles, is not a ray per line).  A hint only: never
    applied."""
    out, names = {}, []
    for name, ax in (axes or {}).items():
        base, unit = _geometry_key(name)
        if base not in _ANGLE_VECTOR_NAMES or n_lines is None or int(ax.get("n", 0)) != int(n_lines):
            continue
        step = abs(float(ax.get("step", 0.0)))
        a = step * {"deg": 1.0, "rad": 180.0 / math.pi}.get(unit, 180.0 / math.pi if step < 0.05 else 1.0)
        if 0.0 < a < 10.0:
            out["angle_pitch_deg"] = a
            names.append(f"{name} = {int(ax['n'])} ray angles {step:g} apart")
            break
    for name, value in fields.items():
        v = _positive(value)
        if v is None:
            continue
        base, unit = _geometry_key(name)
        if base in _RADIUS_NAMES and "radius_mm" not in out:
            out["radius_mm"] = v * {"mm": 1.0, "m": 1e3}.get(unit, 1e3 if v < 0.5 else 1.0)
            names.append(f"{name} = {v:g}")
        elif _is_angle_pitch(base) and "angle_pitch_deg" not in out:
            a = v * {"deg": 1.0, "rad": 180.0 / math.pi}.get(unit, 180.0 / math.pi if v < 0.05 else 1.0)
            if 0.0 < a < 10.0:        # degrees between neighbouring rays, not a field of view
                out["angle_pitch_deg"] = a
                names.append(f"{name} = {v:g}")
    if not out:
        return {}
    return {**out, "names": tuple(names)}


def header_axes(metadata) -> dict:
    """The evenly spaced vectors of a :class:`femreg.io.Frames`' header (:func:`axis_fields`), {} when none."""
    meta = dict(metadata or {})
    return dict(meta.get("axes") or (meta.get("file_metadata") or {}).get("axes") or {})


def header_fields(metadata) -> dict:
    """The header fields of a :class:`femreg.io.Frames`' ``metadata`` (its own, or those of the file it was read
    from), {} when there are none."""
    meta = dict(metadata or {})
    return dict(meta.get("fields") or (meta.get("file_metadata") or {}).get("fields") or {})


def geometry_hint(fields: dict, axes: dict | None = None, n_lines: int | None = None) -> str:
    """The ``--geometry`` flags a file's header fields imply, in words, or "" (:func:`geometry_fields`)."""
    g = geometry_fields(fields, axes, n_lines)
    if not g:
        return ""
    r = g.get("radius_mm")
    # a radius without the angle between rays still means a convex array: the flag is named, its value not known
    pitch = (f"{g['angle_pitch_deg']:.4g}" if "angle_pitch_deg" in g
             else "DEG (the angle between rays, not in the file)")
    flags = (f"--geometry convex --radius {r:.4g} --angle-pitch {pitch}" if r else
             f"--geometry sector --angle-pitch {pitch}")
    kind = "a convex array" if r else "a phased (sector) array, apex on the face"
    return (f"its fields suggest {kind}: {flags} ({', '.join(g['names'])}; radius in mm, angle in degrees): "
            "check them against the probe's specification")


def _positive(value):
    """A field's value as one positive finite float, else None."""
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return None
    if a.size != 1 or not (math.isfinite(float(a.ravel()[0])) and float(a.ravel()[0]) > 0):
        return None
    return float(a.ravel()[0])


# header fields that state where the first sample lies: a receive start time (pulse-echo) or a start depth
_T0_NAMES = ("t0", "starttime", "tstart", "receivestart", "firstsampletime", "timeoffirstsample")
_DEPTH0_NAMES = ("startdepth", "depthstart", "firstsampledepth", "startrange", "rangestart", "r0", "depthoffset",
                 "mindepth", "depthmin")


def origin_hint(fields: dict, sound_speed: float | None = None) -> tuple:
    """``(depth mm, words)`` of the first sample's depth a file's header fields state (a start time ``t0`` read as
    pulse-echo, ``c t0 / 2``; a start depth such as ``start_depth``, ``r0``), or ``(None, "")``.  Units from the
    name's suffix (``_s``, ``_us``, ``_mm``, ``_m``) or else the magnitude (a time below 1e-2 in seconds, else
    microseconds; a depth below 0.5 in metres).  A hint only: readers never apply it (``--origin``)."""
    c = float(sound_speed or 1540.0)
    for name, value in fields.items():
        v = _positive(value)
        if v is None:
            continue
        base, unit = _name_unit(name, ("us", "s", "mm", "m"), _T0_NAMES + _DEPTH0_NAMES)
        if base not in _T0_NAMES + _DEPTH0_NAMES:
            continue
        if base in _T0_NAMES:
            t = v * {"us": 1e-6, "s": 1.0}.get(unit, 1.0 if v < 1e-2 else 1e-6)
            d = c * t / 2.0 * 1e3
            return d, f"{name} = {v:g} read as {t * 1e6:g} us, depth c t0 / 2 at c = {c:g} m/s"
        d = v * {"mm": 1.0, "m": 1e3}.get(unit, 1e3 if v < 0.5 else 1.0)
        return d, f"{name} = {v:g} read as {d:g} mm"
    return None, ""


def unapplied_start_depth(metadata, origin, sound_speed: float | None = None) -> tuple:
    """``(depth mm, words)`` of a start depth the header states (:func:`origin_hint`) that frames read with
    ``metadata`` and ``origin`` do not carry (no ``--origin`` given, the first sample at depth 0), or
    ``(None, "")``."""
    if dict(metadata or {}).get("origin_given") or abs(float(origin[0])) > 0:
        return None, ""
    depth, why = origin_hint(header_fields(metadata), sound_speed)
    return (depth, why) if depth is not None and depth > 0 else (None, "")


def iq_frequency_hint(fields: dict) -> str:
    """The ``--iq-frequency MHZ`` a file's header fields imply, in words, or "".  A field named like a
    demodulation frequency (``f_demod_MHz``, ``demodulation_frequency``, ``modulation_frequency``) first; else the
    probe's centre / transmit frequency (``f0``, ``fc``, ``center_frequency``), at which most IQ exports
    demodulate, named as such.  Units from the name's suffix or else the magnitude (above 1e4: Hz).  A hint
    only: never applied."""
    for names, why in ((_DEMOD_NAMES, ""), (_CENTRE_NAMES, "the probe's centre frequency, at which IQ data are "
                                                           "usually demodulated: check it")):
        for name, value in fields.items():
            v = _positive(value)
            base, unit = _key(name)
            if v is not None and base in names:
                f = _hz(v, unit) / 1e6
                if not 0.1 <= f <= 100.0:  # no ultrasound carrier: not this field
                    continue
                return (f"its fields suggest --iq-frequency {f:.4g} ({name} = {v:g} read as {f:.6g} MHz"
                        f"{'; ' + why if why else ''})")
    return ""


def header_frequencies(metadata) -> dict:
    """The RF sampling rate, transmit (centre) frequency, IQ demodulation frequency and speed of sound a
    :class:`femreg.io.Frames`' header states, as ``{"fs_mhz": (MHz, words), "transmit_mhz": (MHz, words),
    "demod_mhz": (MHz, words), "sound_speed": (m/s, words)}`` with the entries found ({} for none): an Ultrasonix header's ``sf`` and ``txf`` (Hz; 0 is unknown), else the header
    fields (:func:`header_fields`: a Clarius settings file's ``sampling rate`` and ``transmit frequency``, a
    sidecar's ``fs_MHz``, ``f0``, ``center_frequency``, ``c``).  Units from the name's suffix or else the magnitude
    (above 1e4: Hz).  A frequency outside 0.1-1000 MHz is no ultrasound setting and is left out.  What
    :func:`femreg.orientation.check_sampling` holds a given spacing and the RF carrier against."""
    meta = dict(metadata or {})
    inner = dict(meta.get("file_metadata") or {})
    out = {}
    for m in (meta, inner):
        hdr = m.get("header")
        if str(m.get("format", "")) == "ultrasonix" and isinstance(hdr, dict):
            for key, name in (("fs_mhz", "sf"), ("transmit_mhz", "txf")):
                v = _positive(hdr.get(name))
                if v is not None and 0.1 <= v / 1e6 <= 1000.0 and key not in out:
                    out[key] = (v / 1e6, f"its Ultrasonix header's {name} = {v:g} Hz")
    for name, value in header_fields(metadata).items():
        v = _positive(value)
        if v is None:
            continue
        base, unit = _key(name)
        for key, names in (("fs_mhz", _FS_NAMES), ("transmit_mhz", _CENTRE_NAMES), ("demod_mhz", _DEMOD_NAMES)):
            f = _hz(v, unit) / 1e6
            if base in names and key not in out and 0.1 <= f <= 1000.0:
                out[key] = (f, f"its field {name} = {v:g}" + ("" if unit == "mhz" else f", read as {f:g} MHz"))
        if base in _C_NAMES and "sound_speed" not in out and 1000.0 <= v <= 2000.0:
            out["sound_speed"] = (v, f"its field {name} = {v:g} m/s")
    return out


#: Longest vector a reader reads as a possible axis (ray angles, depths), not as data.
AXIS_MAX = 100_000

#: Fewest samples along an axis of an RF frame: an array whose MATLAB-order frame would be thinner, while its
#: first axis read as the frame axis leaves frames at least this size, was written frames first (numpy's order,
#: e.g. ``scipy.io.savemat`` of an ``(n, axial, lateral)`` stack).
MIN_FRAME_SAMPLES = 16


def axis_fields(items, max_size: int = AXIS_MAX) -> dict:
    """{name: {"n", "first", "step"}} of the evenly spaced numeric vectors among ``(name, array)`` pairs (a file's
    axes: ray angles, depths, line positions), 3 to ``max_size`` values, steps equal to 0.1 % of the step; other
    vectors (a TGC curve) are left out.  JSON-friendly, so ``femreg info --json`` prints them."""
    out = {}
    for name, value in items:
        v = np.asarray(value)
        if v.dtype.kind not in "iuf" or not 3 <= v.size <= max_size or sum(d > 1 for d in v.shape) != 1:
            continue
        v = v.astype(float).ravel()
        d = np.diff(v)
        if not np.all(np.isfinite(v)) or d[0] == 0 or np.max(np.abs(d - d[0])) > 1e-3 * abs(d[0]):
            continue
        out[str(name)] = {"n": int(v.size), "first": float(v[0]), "step": float(np.mean(d))}
    return out


def scalar_fields(items) -> dict:
    """{name: value} of the numeric scalars among ``(name, array)`` pairs (a file's header fields), as floats."""
    out = {}
    for name, value in items:
        v = np.asarray(value)
        if v.dtype.kind in "iuf" and v.size == 1:
            out[str(name)] = v.ravel()[0].item()
    return out
