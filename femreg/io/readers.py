"""One entry point, :func:`read_frames`, for every RF frame format femreg reads.

Formats (chosen by extension, verified by content):

=====================  ============================================================================
``.npy``               2D (axial, lateral) or 3D (n, axial, lateral) array; no spacing stored
``.npz``               key ``rf`` or ``frames`` (or ``variable=``), optional ``spacing``, ``origin``
``.mat``               MATLAB v5/v7 (femreg's pure-Python reader), v4 (scipy.io) or v7.3 (HDF5, h5py); see
                       :mod:`femreg.io.matlab`
``.mhd`` / ``.mha``    MetaImage header + data; see :mod:`femreg.io.metaimage` for the axis mapping
``.raw`` ``.bin``...   headerless samples: ``shape`` required, ``dtype`` (default float32), ``byte_order``
``.rf``                Ultrasonix RF (76-byte header, int16); see :mod:`femreg.io.ultrasonix`
``.raw`` (Clarius)     a Clarius research export (5-field header, time-stamped int16 frames stored line by line,
                       told by its size), settings from the YAML beside it; see :mod:`femreg.io.clarius`
``.uff``               USTB's Ultrasound File Format (HDF5): beamformed frames and their scan, IQ remodulated
                       to RF; see :mod:`femreg.io.uff`
``.h5`` ``.hdf5``      plain HDF5: a dataset of frames, its layout told by the RF carrier; see :mod:`femreg.io.hdf5`
``.dcm`` ``.dicom``    DICOM ultrasound image or cine loop (also any file with ``DICM`` at byte 128): B-mode frames
                       cropped to the tissue region, spacing from its calibration; needs pydicom (the ``dicom``
                       extra); see :mod:`femreg.io.dicom`
directory              one file per frame (e.g. ``frame1.raw ... frame6.raw``), natural sort of names; DICOM files
                       by ``InstanceNumber``
=====================  ============================================================================

Volumes (:func:`read_volumes` -> :class:`~femreg.io.Volumes`, ``(n, axial, lateral, elevational)``): npy, npz
(keys ``rf``, ``frames``, ``volume`` or ``volumes``; ``spacing`` of three values), mat (``rf(axial, lateral,
elevational[, frame])``, frames last as MATLAB's 2D layout) and MetaImage (NDims 3 or 4).  A 3-dimensional
array is one volume and a 4-dimensional one a sequence with the frames first (npy, npz) as the 2D
``(n, axial, lateral)`` layout; :func:`read_frames` reads 3-dimensional arrays as 2D frame sequences, so the two
readers never guess: a file whose stored spacing has the other reader's number of values is refused with a
message naming the right one.

Every failure is a :class:`~femreg.errors.FileFormatError` (bad file) or :class:`~femreg.errors.InputError`
(bad arguments), both ``ValueError`` subclasses, with a one-line message naming the file and the problem.
"""
from __future__ import annotations

import math
import os
import zipfile
from pathlib import Path

import numpy as np

from ..errors import FileFormatError, InputError, pass_as
from .checks import FORMATS, parse_dtype  # noqa: F401  (API)
from .checks import axis_fields, check_origin, fail, merge_spacing, natural_key, scalar_fields, spacing_suggestion
from .frames import Frames, Volumes, finalize, finalize_volumes

__all__ = ["read_frames", "read_volumes", "FORMATS", "detect_format", "parse_dtype"]

_MAGIC = [(b"\x93NUMPY", "npy"), (b"PK\x03\x04", "npz"), (b"PK\x05\x06", "npz"), (b"MATLAB", "mat"),
          (b"\x89HDF\r\n\x1a\n", "hdf5")]
#: Formats stored as HDF5 (a file of one may be read by another's reader).
_HDF5_FORMATS = ("mat", "uff", "hdf5")
PREFERRED_KEYS = ("rf", "frames")
_MAX_BYTES = 1 << 34  # refuse arrays claiming more than 16 GiB (a corrupt header, not RF)

def _check_shape(shape):
    if shape is None:
        return None
    try:
        vals = tuple(int(s) for s in np.asarray(shape).ravel())
        if any(float(a) != b for a, b in zip(np.asarray(shape).ravel(), vals)):
            raise ValueError
    except (TypeError, ValueError):
        raise InputError(f"shape must be integers (axial, lateral) or (n, axial, lateral), got {shape!r}") from None
    if len(vals) not in (2, 3) or min(vals) < 1:
        raise InputError(f"shape must be 2 or 3 positive integers (axial, lateral) or (n, axial, lateral), "
                         f"got {shape!r}")
    return vals


def detect_format(path) -> str:
    """Format name from the extension, else from the first bytes; FileFormatError if neither tells."""
    path = Path(path)
    if path.is_dir():
        return "directory"
    fmt = FORMATS.get(path.suffix.lower())
    if fmt:
        return fmt
    try:
        with open(path, "rb") as fh:
            head = fh.read(1024)
    except OSError as exc:
        raise fail(path, f"cannot read ({exc.strerror or exc})") from None
    for magic, name in _MAGIC:
        if head.startswith(magic) or (name == "hdf5" and head[512:520] == magic):
            return name
    if head[128:132] == b"DICM":        # DICOM's preamble marker (files named IM_0001, or by UID)
        return "dicom"
    if head[:80].lstrip().lower().startswith((b"objecttype", b"ndims")):
        return "metaimage"
    raise fail(path, f"unknown file type {path.suffix!r}; supported: " + ", ".join(sorted(FORMATS))
               + ", or a directory of frame files")


def _sniff_mislabel(path, head: bytes, fmt: str):
    for magic, name in _MAGIC:
        if name != fmt and head.startswith(magic) and not (fmt in _HDF5_FORMATS and name in _HDF5_FORMATS):
            raise fail(path, f"content is a {name} file, not {fmt} as the extension says")


# ----------------------------------------------------------------------------------------------- npy / npz

def _parse_npy(fh, size: int, path, label: str):
    """Read one .npy stream of ``size`` bytes with header validation before any allocation."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = fmt.read_array_header_1_0(fh, max_header_size=100_000)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = fmt.read_array_header_2_0(fh, max_header_size=100_000)
        else:
            raise ValueError(f"unsupported .npy version {version}")
    except MemoryError:
        raise
    except Exception as exc:  # ValueError, EOFError, SyntaxError, tokenize.TokenError, UnicodeDecodeError...
        raise fail(path, f"{label}: bad .npy header ({type(exc).__name__}: {exc})") from None
    if dtype.hasobject or dtype.names is not None or dtype.subdtype is not None:
        raise fail(path, f"{label}: dtype {dtype} is not a plain numeric array (object arrays are never loaded)")
    if dtype.kind not in "biufc":
        raise fail(path, f"{label}: dtype {dtype} is not numeric")
    count = int(np.prod(shape, dtype=np.int64)) if shape else 1
    nbytes = count * dtype.itemsize
    if nbytes > _MAX_BYTES:
        raise fail(path, f"{label}: header claims {shape} {dtype}, over 16 GiB")
    pos = fh.tell()
    avail = size - pos
    if avail < nbytes:
        raise fail(path, f"{label}: truncated, {avail} data bytes for {shape} {dtype} ({nbytes} bytes)")
    blob = fh.read(nbytes)
    if len(blob) != nbytes:
        raise fail(path, f"{label}: truncated, {len(blob)} data bytes for {shape} {dtype} ({nbytes} bytes)")
    arr = np.frombuffer(blob, dtype=dtype)
    return arr.reshape(shape[::-1]).T if fortran else arr.reshape(shape)


def read_npy(path, *, spacing=None, frames=None, **_ignored):
    path = Path(path)
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as fh:
            arr = _parse_npy(fh, size, path, "npy")
    except OSError as exc:
        raise fail(path, f"cannot read ({exc.strerror or exc})") from None
    suggestion, side = _sidecar(path)
    sp = merge_spacing(path, None, spacing, required_msg=".npy stores no spacing", frame_shape=arr.shape[-2:],
                       suggestion=suggestion)
    return finalize(path, arr, sp, (0.0, 0.0), {"format": "npy", **side}, frames)


_SIDECAR_KEY = "\0sidecar"


def _sidecar(path) -> tuple:
    """``(suggestion, metadata)`` of a headerless file's JSON sidecar (:func:`sidecar_fields`): the spacing its
    fields imply (:func:`~femreg.io.checks.spacing_suggestion`, or None) and the metadata entries ``sidecar``
    (its name, or why it could not be read) and ``fields`` ({} without a sidecar)."""
    fields = sidecar_fields(path)
    if not fields:
        return None, {}
    suggestion = spacing_suggestion(fields)
    meta = {"sidecar": fields.pop(_SIDECAR_KEY)}
    if fields:
        meta["fields"] = fields
    return suggestion, meta


def sidecar_fields(path) -> dict:
    """Numeric scalars of a JSON sidecar beside a headerless file (``scan.json`` or ``scan.npy.json`` beside
    ``scan.npy``, likewise ``.raw``), nested objects' keys joined by ``/`` as a .mat file's struct fields: header
    fields that :func:`~femreg.io.checks.spacing_suggestion` reads (``fs`` Hz, ``c`` m/s, ``pitch`` m).  They only
    inform (never applied); {} without a sidecar, else the sidecar's name (and why it could not be read) under a
    private key."""
    import json

    path = Path(path)
    for side in (path.with_suffix(".json"), path.with_name(path.name + ".json")):
        if side.is_file() and not side.name.endswith(".femreg.json"):   # batch's own settings file
            try:
                data = json.loads(side.read_text())
            except (OSError, ValueError) as exc:    # said by femreg info, not fatal: the frames are read
                return {_SIDECAR_KEY: f"{side.name} not read ({type(exc).__name__}: {exc})"}
            out = {}

            def walk(d, pre=""):
                for k, v in d.items():
                    if isinstance(v, dict):
                        walk(v, f"{pre}{k}/")
                    elif isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
                        out[f"{pre}{k}"] = v

            if isinstance(data, dict):
                walk(data)
            if out:
                out[_SIDECAR_KEY] = side.name
            return out
    return {}


def _load_npz(path, variable, preferred):
    """(array, raw spacing or None, raw origin or None, key, sorted member names) of an .npz file."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as zf:
            members = {}
            for info in zf.infolist():
                name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
                members[name] = info
            if variable is not None:
                if variable not in members:
                    raise fail(path, f"missing variable {variable!r}; keys: {', '.join(sorted(members)) or 'none'}")
                key = variable
            else:
                key = next((k for k in preferred if k in members), None)
                if key is None and {"mesh_points", "mesh_cells"} <= set(members):
                    kind, readers = (("inversion", "plot and measure") if "mu" in members else
                                     ("registration", "plot, measure and invert"))
                    raise fail(path, f"a femreg {kind} result (mesh and fields), not RF frames: pass the frame "
                                     f"files it was computed from; femreg {readers} read it")
                if key is None and {"exx", "ref_frame"} <= set(members):
                    raise fail(path, "a femreg elastogram (strain image), not RF frames: pass the frame files it "
                                     "was computed from; femreg measure reads it")
                if key is None:
                    raise fail(path, f"no {' or '.join(repr(k) for k in preferred)} array; keys: "
                                     f"{', '.join(sorted(members)) or 'none'} (choose one with variable= / --variable)")

            def load(k):
                info = members[k]
                with zf.open(info) as fh:
                    return _parse_npy(fh, info.file_size, path, f"key {k!r}")

            arr = load(key)
            raw_sp = np.asarray(load("spacing")) if "spacing" in members and key != "spacing" else None
            raw_origin = np.asarray(load("origin")) if "origin" in members and key != "origin" else None
            other = sorted(members)
    except (FileFormatError, InputError):
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError, ValueError, NotImplementedError,
            RuntimeError, KeyError, UnicodeDecodeError) as exc:
        raise fail(path, f"corrupt or truncated .npz ({type(exc).__name__}: {exc})") from None
    return arr, raw_sp, raw_origin, key, other


def _npz_spacing(path, sp, n):
    if sp is None:
        return None
    if sp.dtype.kind not in "iuf" or sp.size != n:
        names = "(dx, dy)" if n == 2 else "(dx, dy, dz)"
        hint = ""
        if n == 2 and sp.dtype.kind in "iuf" and sp.size == 3:
            hint = " (three values: a volume; read it with femreg.io.read_volumes)"
        elif n == 3 and sp.dtype.kind in "iuf" and sp.size == 2:
            hint = " (two values: 2D frames; read them with femreg.io.read_frames)"
        raise fail(path, f"key 'spacing' must hold {('two', 'three')[n - 2]} numbers {names} mm, got "
                         f"{sp.dtype} {sp.shape}{hint}")
    return tuple(float(v) for v in sp.ravel())


def read_npz(path, *, variable=None, spacing=None, frames=None, **_ignored):
    path = Path(path)
    arr, raw_sp, raw_origin, key, other = _load_npz(path, variable, PREFERRED_KEYS)
    file_spacing = _npz_spacing(path, raw_sp, 2)
    origin = check_origin(raw_origin, path) if raw_origin is not None else None
    small = _npz_small(path, key)
    fields, axes = scalar_fields(small), axis_fields(small)
    sp = merge_spacing(path, file_spacing, spacing, required_msg="the .npz has no 'spacing' key",
                       suggestion=spacing_suggestion(fields) if file_spacing is None else None,
                       frame_shape=arr.shape[-2:])
    meta = {"format": "npz", "variable": key, "keys": other, **({"fields": fields} if fields else {}),
            **({"axes": axes} if axes else {})}
    return finalize(path, arr, sp, origin, meta, frames)


def _npz_small(path, key) -> list:
    """``(name, array)`` of the small members of an .npz besides ``key`` (header fields such as ``fs``, ``pitch``,
    axes such as a scan's ``theta``); members under 1 MiB only, so the frames are not read twice.  [] if they
    cannot be read: they only inform."""
    try:
        with zipfile.ZipFile(path) as zf:
            small = [i for i in zf.infolist() if i.file_size < 1 << 20 and i.filename[:-4] not in (key, "spacing",
                                                                                                    "origin")]
            items = []
            for info in small:
                with zf.open(info) as fh:
                    items.append((info.filename[:-4] if info.filename.endswith(".npy") else info.filename,
                                  np.lib.format.read_array(fh, allow_pickle=False)))
    except Exception:  # header fields only inform: the frames were read already
        return []
    return items


# --------------------------------------------------------------------------------------------------- raw

def read_raw(path, *, shape=None, dtype=None, byte_order=None, spacing=None, frames=None, offset=0, **_ignored):
    """Headerless samples.  ``shape`` (axial, lateral) reads as many whole frames as the file holds;
    (n, axial, lateral) requires exactly n.  Layout C-order: lateral fastest (as ``np.fromfile(...).reshape``)."""
    path = Path(path)
    if not offset:
        from .clarius import _header, cut_short, read_clarius, sniff

        head = _header(path)            # the first bytes, read once for both questions below
        if (hdr := sniff(path, head)) is not None:     # a Clarius export: its header states the shape and type
            return read_clarius(path, shape=shape, dtype=dtype, spacing=spacing, frames=frames, header=hdr)
        if shape is None:
            cut = cut_short(path, head)
            if cut:
                raise fail(path, cut)
    shp = _check_shape(shape)
    if shp is None:
        sibling = path.with_suffix(".mhd")
        if sibling.exists():
            from .metaimage import read_metaimage

            return Frames(**read_metaimage(sibling, spacing=spacing, frames=frames))
        from .rawlayout import guess_shape

        hint = guess_shape(path, offset=offset, dtype=dtype, byte_order=byte_order)
        raise InputError(f"{path}: raw file needs "
                         + pass_as("shape=(axial, lateral) (CLI: --shape NAX NLAT)",
                                   "--shape NAX NLAT (axial, lateral)")
                         + "; "
                         "no header to read it from" + (f"; {hint}" if hint else ""))
    dt = parse_dtype(dtype, byte_order)
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as fh:
            head = fh.read(8)
    except OSError as exc:
        raise fail(path, f"cannot read ({exc.strerror or exc})") from None
    _sniff_mislabel(path, head, "raw")
    body = size - int(offset)
    frame_bytes = shp[-2] * shp[-1] * dt.itemsize
    if len(shp) == 3 and min(shp[1:]) < 2:
        # three numbers are FRAMES AXIAL LATERAL: AXIAL LATERAL FRAMES leaves frames one sample wide
        f, a, b = shp[2], shp[0], shp[1]
        hint = f", e.g. {pass_as(f'({f}, {a}, {b})', f'--shape {f} {a} {b}')}" if shp[2] < 2 else ""
        raise fail(path, f"shape {shp} reads {shp[0]} frame(s) of {shp[1]} x {shp[2]} samples, one sample wide: "
                         "with three numbers " + pass_as("shape is (frames, axial, lateral)",
                                                         "--shape is FRAMES AXIAL LATERAL") + hint)
    if len(shp) == 3:
        need = shp[0] * frame_bytes
        if body != need:
            kind = "truncated" if body < need else "size mismatch"
            raise fail(path, f"{kind}: {body} bytes, shape {shp} {dt.name} needs {need}"
                             + _surplus_hint(body, frame_bytes, shp[0]))
        n = shp[0]
    else:
        if body <= 0 or body % frame_bytes:
            hint = ""
            fits = [np.dtype(dt.byteorder.replace("=", "<").replace("|", "<") + alt) for alt in ("i2", "f4", "f8")
                    if alt != dt.str[1:] and body > 0 and body % (shp[0] * shp[1] * np.dtype(alt).itemsize) == 0]
            if fits:                        # the type whose samples show an RF carrier first, if one does
                from .rawlayout import shows_carrier

                best = next((t for t in fits if shows_carrier(path, shp, t, offset=offset)), None)
                name = (best or fits[0]).name
                shows = " whose samples show an RF carrier" if best is not None else ""
                hint = (f" (a whole number of {name} frames{shows}: try "
                        + pass_as(f"dtype={name}, CLI: --dtype {name}", f"--dtype {name}") + ")")
            raise fail(path, f"size mismatch: {body} bytes is not a whole number of {shp[0]} x {shp[1]} {dt.name} "
                             f"frames ({frame_bytes} bytes each){hint or _surplus_hint(body, frame_bytes)}")
        n = body // frame_bytes
    if n * frame_bytes > _MAX_BYTES:
        raise fail(path, "over 16 GiB of samples; select frames or split the file")
    try:
        arr = np.fromfile(path, dtype=dt, count=n * shp[-2] * shp[-1], offset=int(offset))
    except (OSError, ValueError) as exc:
        raise fail(path, f"cannot read samples ({exc})") from None
    arr = arr.reshape(n, shp[-2], shp[-1])
    from .rawlayout import byte_order_hint, carrier_axis, continued_frames, dtype_hint, resolve_layout

    with np.errstate(all="ignore"):                   # swapped bytes read as huge values: no warnings
        axis = carrier_axis(arr[0])                   # the carrier test, once for both checks
    swap = byte_order_hint(arr[0], dt, axis=axis) or dtype_hint(path, shp, dt, offset=offset, axis=axis,
                                                                 first=arr[0])
    if swap:
        raise fail(path, swap)
    arr, layout = resolve_layout(arr, path, axis=axis)
    # RF only: envelope rows far apart can be alike (a shadow down the image), RF rows carry random phases
    pieces = continued_frames(arr) if axis is not None else ""
    if pieces:
        raise fail(path, pieces)
    suggestion, side = _sidecar(path)
    sp = merge_spacing(path, None, spacing, required_msg="raw files store no spacing", frame_shape=arr.shape[-2:],
                       suggestion=suggestion)
    meta = {"format": "raw", "dtype": dt.name, "byte_order": "big" if dt.byteorder == ">" else "little", **side}
    if layout:
        meta["layout"] = layout
    return finalize(path, arr, sp, (0.0, 0.0), meta, frames)


def _surplus_hint(body: int, frame_bytes: int, n_frames: int | None = None) -> str:
    """Where a headerless read leaves bytes over: how many, beyond how many whole frames, and that they look like
    a header (a file header and/or one before each frame), which a raw read cannot skip; "" otherwise."""
    n = body // frame_bytes if n_frames is None else int(n_frames)
    extra = body - n * frame_bytes
    if n < 1 or extra <= 0 or extra >= frame_bytes:
        return ""
    return (f"; {extra} bytes over {n} whole frame(s), as a header would leave (before the data, or before each "
            "frame), which a headerless read cannot skip.  femreg reads the headers of Ultrasonix .rf and Clarius "
            "raw exports (femreg info FILE names the format); other files: write the samples alone")


# ------------------------------------------------------------------------------------------- directories

def is_result_file(path) -> bool:
    """True for an ``.npz`` that femreg wrote as a result (registration, volume or inversion: it holds
    ``mesh_points`` and ``mesh_cells``), read from the archive's index only."""
    path = Path(path)
    if path.suffix.lower() != ".npz":
        return False
    try:
        with np.load(path, allow_pickle=False) as z:
            return {"mesh_points", "mesh_cells"} <= set(z.files)
    except Exception:  # not a readable npz: read_frames says why if it is ever read as frames
        return False


def read_directory(path, *, frames=None, **options):
    """One file per frame (or per sub-sequence), files of one format, natural order of their names.

    femreg's own result files in the folder (``femreg register ... -o pair.npz`` written beside the frames) are
    set aside, not read as frames; their names are in ``metadata["set_aside"]``.
    """
    path = Path(path)
    try:
        entries = [p for p in path.iterdir() if p.is_file() and not p.name.startswith(".")]
    except OSError as exc:
        raise fail(path, f"cannot list directory ({exc.strerror or exc})") from None
    by_ext: dict[str, list[Path]] = {}
    set_aside = []
    for p in entries:
        if p.suffix.lower() in FORMATS:
            if is_result_file(p):
                set_aside.append(p.name)
                continue
            by_ext.setdefault(FORMATS[p.suffix.lower()], []).append(p)
    set_aside.sort(key=natural_key)
    if set(by_ext) <= {"dicom"}:        # clinical exports name DICOM files without an extension (IM_0001)
        from .dicom import dicom_files

        found = dicom_files(path)
        if found:
            by_ext["dicom"] = found
    if "metaimage" in by_ext:  # the .raw files are the headers' data files
        by_ext.pop("raw", None)
    if not by_ext:
        aside = f"; {len(set_aside)} femreg result file(s) set aside ({', '.join(set_aside[:3])}" + (
            ", ...)" if len(set_aside) > 3 else ")") if set_aside else ""
        subs = sorted((q.name for q in path.iterdir() if q.is_dir() and not q.name.startswith(".")),
                      key=natural_key)
        inside = (f"; it holds folders ({', '.join(subs[:3])}{', ...' if len(subs) > 3 else ''}): pass one of "
                  f"them (femreg batch: each is a recording without --folders recording)") if subs else ""
        raise fail(path, "directory holds no frame files (" + ", ".join(sorted(FORMATS)) + ")" + aside + inside)
    if len(by_ext) > 1:
        listing = "; ".join(f"{fmt}: {', '.join(sorted((q.name for q in fs), key=natural_key)[:3])}"
                            + (", ..." if len(fs) > 3 else "") for fmt, fs in sorted(by_ext.items()))
        raise fail(path, f"directory mixes formats ({listing}); point at one file or move the others out")
    (fmt, files), = by_ext.items()
    files.sort(key=lambda p: natural_key(p.name))
    if fmt == "raw" and len(files) > 1:
        from .clarius import sniff

        loops = [(f, sniff(f)) for f in files]
        loops = [(f, h) for f, h in loops if h is not None]
        if loops:   # an unpacked Clarius export: RF and envelope loops side by side, not one frame per file
            listing = "; ".join(f"{f.name}: {'RF' if h['samplesize'] == 2 else 'envelope'}, {h['frames']} frame(s) "
                                f"of {h['samples']} x {h['lines']}" for f, h in loops[:3])
            rf = next((f for f, h in loops if h["samplesize"] == 2), loops[0][0])
            raise fail(path, f"directory holds Clarius exports, each a whole loop ({listing}"
                             f"{'; ...' if len(loops) > 3 else ''}): pass one file, e.g. {rf}")
    if fmt == "dicom":                  # one series, in InstanceNumber order
        from .dicom import read_dicom_series

        return Frames(**read_dicom_series(path, files, frames=frames, **options))
    parts = [_read_stored(f, **options) for f in files]        # IQ stays complex: read_frames remodulates the stack
    first = parts[0]
    for f, part in zip(files[1:], parts[1:]):
        if part.shape != first.shape:
            raise fail(f, f"frame shape {part.shape} differs from {files[0].name}'s {first.shape}")
        if not np.allclose(part.spacing, first.spacing, rtol=1e-9):
            raise fail(f, f"spacing {part.spacing} differs from {files[0].name}'s {first.spacing}")
    dt = np.result_type(*(p.frames.dtype for p in parts))
    stack = np.concatenate([p.frames.astype(dt, copy=False) for p in parts], axis=0)
    meta = {"format": f"directory of {fmt}", "files": [f.name for f in files],
            "file_metadata": first.metadata, "set_aside": set_aside}
    return finalize(path, stack, first.spacing, first.origin, meta, frames)


# ------------------------------------------------------------------------------------------- entry point

def read_frames(path, *, variable=None, shape=None, dtype=None, spacing=None, byte_order=None, frames=None,
                sound_speed=None, modulation_frequency=None, iq_conjugate=False, check_orientation=True,
                origin=None, transpose=False) -> Frames:
    """Read RF frames from ``path`` (a file, or a directory of per-frame files).

    Parameters
    ----------
    path : str or Path
        File (format from its extension, checked against its content) or directory (see module docstring).
    variable : str, optional
        Array name in .npz / .mat files (default ``rf`` or ``frames``, else the only 2D/3D numeric array).
    shape : (axial, lateral) or (n, axial, lateral), optional
        Required for headerless raw files (ignored where a header gives the shape).
    dtype : str, optional
        On-disk sample type of raw files (default float32): float32, float64, int16, uint16, int8, ...
    spacing : (dx, dy) mm, optional
        Axial and lateral pixel spacing; overrides the file's (a None entry keeps the file's value).
        Required where the file stores none (npy, raw, the lateral pitch of Ultrasonix .rf).  Where the file's
        own calibration states one (a DICOM ultrasound region), a value more than 1 % from it is refused unless
        ``check_orientation`` is False.
    byte_order : {'little', 'big'}, optional
        Raw files only (default little); headers say their own.
    frames : int, slice or sequence of int, optional
        Frame selection (default all).
    sound_speed : float, m/s, optional
        For the axial spacing of Ultrasonix files, ``c / (2 fs)`` (default 1540), and the remodulation of IQ data.
    modulation_frequency : float, MHz, optional
        IQ data (complex samples, in any format that stores complex arrays: npy, npz, mat, uff) are remodulated to
        RF with this demodulation frequency (:func:`femreg.io.iq.remodulate`; the axial spacing becomes the RF
        grid's, ``metadata["iq"]`` records how).  Required for complex data, except UFF files that store their
        own (this value overrides it); refused for real (RF) data.
    iq_conjugate : bool
        IQ data demodulated with ``exp(+2 pi i f t)`` (the opposite of the usual convention): conjugated first.
    origin : (x0, y0) mm, optional
        Position of sample ``[0, 0]`` (depth of the first sample, lateral position of the first line; for a
        convex / sector frame the first range and 0); overrides the file's (default: the file's, else (0, 0)).
        A header field such as ``t0`` or ``start_depth`` is named by :func:`femreg.io.checks.origin_hint`, not
        applied here (the command line applies it to convex / sector frames only, whose geometry needs it).
    transpose : bool
        Frames stored (lateral lines, axial samples), e.g. written from MATLAB or saved as ``frame.T``: each frame
        is transposed to (axial, lateral) as read.  A given ``spacing`` is that of the transposed frames (axial,
        lateral); a spacing the file stores goes with its axes (exchanged too).
    check_orientation : bool
        Refuse a ``spacing`` that contradicts the file's calibration (above) or its header's RF sampling rate or
        transmit frequency (:func:`femreg.orientation.check_sampling`; a milder mismatch of the carrier with the
        transmit frequency is noted in ``metadata["sampling_notes"]``), and a raw file read with its two
        sizes exchanged (``shape`` given lines first: the frames come out scrambled,
        :func:`femreg.orientation.check_raw_shape`).  IQ data: refuse spacings that look
        exchanged (:func:`femreg.orientation.check_remodulated`; the RF checks of :func:`femreg.register` cannot
        see them once the carrier comes from the modulation frequency) and, from frames 0 and 1, the other sign
        convention (:func:`femreg.orientation.check_iq_sign`).

    Returns
    -------
    Frames
        ``frames`` (n, axial, lateral) float32/float64, finite; ``spacing`` (dx, dy) mm; ``origin``;
        ``metadata`` (format, header fields); ``source``.

    Raises
    ------
    FileFormatError
        The file is missing, truncated, corrupt, mislabelled, or holds NaN/Inf.
    InputError
        A bad or missing argument (e.g. spacing needed but not given).
    """
    options = dict(variable=variable, shape=shape, dtype=dtype, spacing=spacing, byte_order=byte_order,
                   sound_speed=sound_speed, modulation_frequency=modulation_frequency, iq_conjugate=iq_conjugate)
    stored = _read_stored(path, frames=frames, **options)
    if transpose:
        stored = _transposed(stored, spacing)
    fr = _rf_from_iq(stored, modulation_frequency, sound_speed, iq_conjugate)
    if check_orientation:       # a raw frame read with its sizes exchanged is scrambled, and registers as envelope
        from ..orientation import OrientationError, check_raw_shape

        try:
            check_raw_shape(fr)
        except OrientationError as exc:
            raise OrientationError(f"{fr.source}: {exc}", problem=exc.problem) from None
    if check_orientation and spacing is not None:
        _check_given_spacing(fr, spacing)
    if check_orientation:       # the axial spacing against the header's sampling rate and transmit frequency
        from ..orientation import check_sampling

        notes = check_sampling(fr, spacing, sound_speed=sound_speed, where=f"{fr.source}: ")
        if notes:
            fr.metadata["sampling_notes"] = notes
    if origin is not None:
        fr.origin = check_origin(origin)
        fr.metadata["origin_given"] = True
    if check_orientation and "iq" in fr.metadata:
        from ..orientation import check_iq_sign, check_remodulated

        check_remodulated(fr)
        if fr.n_frames >= 2:
            fr.metadata["iq"]["convention_check"] = list(check_iq_sign(fr.frames[0], fr.frames[1], fr.spacing,
                                                                       fr.metadata["iq"], where=f"{fr.source}: ",
                                                                       metadata=fr.metadata))
    return fr


def _transposed(fr: Frames, spacing) -> Frames:
    """``fr`` with every frame transposed, (n, a, b) -> (n, b, a); the file's own spacing exchanged with its axes,
    a given ``spacing`` (already axial, lateral) kept.  One value given and one taken from the file would mix the
    two orders: refused."""
    a = np.asarray(fr.frames)
    if a.ndim != 3:
        raise InputError(f"{fr.source}: transpose applies to frames (n, samples, lines), got an array of shape "
                         f"{a.shape}")
    if spacing is not None and any(v is None for v in spacing):
        raise InputError(f"{fr.source}: with --transpose give both spacings (axial, lateral of the transposed "
                         "frames): 'auto' for one of them would take the file's value for the other axis")
    fr.frames = np.ascontiguousarray(a.transpose(0, 2, 1))
    if spacing is None and fr.spacing is not None and len(fr.spacing) == 2:
        fr.spacing = (float(fr.spacing[1]), float(fr.spacing[0]))
    # the file's calibration and origin go with its axes too: a given spacing (axial, lateral of the transposed
    # frames) is compared with the calibration in that order
    header = fr.metadata.get("header_spacing")
    if header is not None and len(header) == 2:
        fr.metadata["header_spacing"] = [header[1], header[0]]
        if fr.metadata.get("spacing_source"):
            fr.metadata["spacing_source"] += " (of the file's axes, exchanged with them: transposed)"
    if fr.origin is not None and len(fr.origin) == 2:
        fr.origin = (float(fr.origin[1]), float(fr.origin[0]))
    what = "each frame transposed as read (" + pass_as("transpose=True; CLI --transpose", "--transpose") + ")"
    fr.metadata["layout"] = f"{fr.metadata['layout']}; {what}" if fr.metadata.get("layout") else what
    return fr


#: A given spacing further than this (relative) from the one a file's calibration states is refused.
SPACING_TOLERANCE = 0.01


def _check_given_spacing(fr: Frames, spacing) -> None:
    """InputError when a given spacing differs by more than :data:`SPACING_TOLERANCE` from the spacing the file's
    own calibration states (``metadata["header_spacing"]``, a DICOM ultrasound region's): a wrong spacing scales
    every displacement and strain and passes the speckle checks."""
    header = fr.metadata.get("header_spacing")
    if header is None:
        return
    from ..orientation import override
    from .checks import check_spacing

    given = check_spacing(spacing, allow_none=True)
    wrong = [f"{name} {g:g} mm against {h:.6g} mm" for name, g, h in zip(("axial", "lateral"), given, header)
             if g is not None and abs(g / h - 1.0) > SPACING_TOLERANCE]
    if wrong:
        raise InputError(f"{fr.source}: the spacing given contradicts the file's calibration ({'; '.join(wrong)}; "
                         f"{fr.metadata.get('spacing_source', 'its header')}): leave --spacing out to use the "
                         f"file's, or {override()} to use the values given")


def _read_stored(path, *, frames=None, **options) -> Frames:
    """The frames of ``path`` as stored (IQ data still complex): format detection, the reader, typed errors."""
    try:
        path = Path(os.fspath(path))
    except TypeError:
        raise InputError(f"path must be a file name, got {path!r}") from None
    if not path.exists():
        raise fail(path, "no such file or directory")
    fmt = "unknown"
    try:
        fmt = detect_format(path)
        if fmt == "directory":
            return read_directory(path, frames=frames, **options)
        if not path.is_file():
            raise fail(path, "not a regular file")
        if fmt != "raw":
            with open(path, "rb") as fh:
                head = fh.read(8)
            if not head:
                raise fail(path, f"empty file (expected {fmt})")
            _sniff_mislabel(path, head, fmt)
        return _READERS[fmt](path, frames=frames, **options)
    except (FileFormatError, InputError):
        raise
    except MemoryError:
        raise fail(path, f"not enough memory to read this {fmt} file (corrupt header or too large)") from None
    except Exception as exc:  # last line of defence: never let a library exception escape untyped
        raise fail(path, f"cannot read {fmt} file ({type(exc).__name__}: {exc})") from None


def _rf_from_iq(fr: Frames, modulation_frequency, sound_speed, conjugate=False) -> Frames:
    """``fr`` with complex (IQ) samples remodulated to RF (:func:`femreg.io.iq.remodulate`); a clear error for IQ
    without its modulation frequency, or a modulation frequency given for RF."""
    if not np.iscomplexobj(fr.frames):
        remodulated = fr.metadata.get("remodulated") or dict(fr.metadata.get("file_metadata") or {}).get("remodulated")
        if modulation_frequency is not None and not remodulated:
            raise InputError(f"{fr.source}: a modulation frequency was given but the samples are real "
                             f"({fr.metadata.get('stored_dtype', fr.frames.dtype)}): RF, not IQ; leave it out")
        return fr
    if modulation_frequency is None:
        from .checks import iq_frequency_hint

        hint = iq_frequency_hint(fr.metadata.get("fields") or {})
        exc = InputError(f"{fr.source}: complex samples ({fr.metadata.get('stored_dtype', fr.frames.dtype)}): IQ "
                         "data, not RF. Give the demodulation frequency (the scanner's IQ export records it) to "
                         "remodulate them to RF: "
                         + pass_as("read_frames(..., modulation_frequency=MHZ) (CLI: --iq-frequency MHZ)",
                                   "--iq-frequency MHZ")
                         + (f"; {hint}" if hint else ""))
        exc.iq_frames = fr          # what was read, for a description of the file (femreg info)
        raise exc
    from .iq import SOUND_SPEED, remodulate

    c = SOUND_SPEED if sound_speed is None else float(sound_speed)
    rf, dx, up = remodulate(fr.frames, fr.spacing[0], modulation_frequency, axial_origin=fr.origin[0],
                            sound_speed=c, axis=1, conjugate=bool(conjugate))
    meta = {**fr.metadata, "remodulated": True,
            "iq": {"modulation_frequency_mhz": float(modulation_frequency), "sound_speed": c, "upsampled": up,
                   "conjugate": bool(conjugate),
                   "iq_spacing_mm": fr.spacing[0], "iq_samples": int(fr.frames.shape[1])}}
    return Frames(frames=np.ascontiguousarray(rf), spacing=(dx, fr.spacing[1]), origin=fr.origin, metadata=meta,
                  source=fr.source)


def _read_mat(path, **kw):
    from .matlab import read_mat

    return Frames(**read_mat(path, **kw))


def _read_mhd(path, **kw):
    from .metaimage import read_metaimage

    return Frames(**read_metaimage(path, **kw))


def _read_rf(path, **kw):
    from .ultrasonix import read_ultrasonix

    return Frames(**read_ultrasonix(path, **kw))


def _read_uff(path, **kw):
    from .uff import read_uff

    return Frames(**read_uff(path, **kw))


def _read_dicom(path, **kw):
    from .dicom import read_dicom

    return Frames(**read_dicom(path, **kw))


def _read_hdf5(path, **kw):
    from .hdf5 import read_hdf5
    from .matlab import mat_version

    with open(path, "rb") as fh:
        if fh.read(6) == b"MATLAB" and mat_version(path) == "7.3":     # MATLAB's -v7.3 under another name
            return _read_mat(path, **kw)
    return Frames(**read_hdf5(path, **kw))


_READERS = {"npy": read_npy, "npz": read_npz, "mat": _read_mat, "metaimage": _read_mhd, "raw": read_raw,
            "ultrasonix": _read_rf, "uff": _read_uff, "hdf5": _read_hdf5, "dicom": _read_dicom}


# ------------------------------------------------------------------------------------------------ volumes

VOLUME_KEYS = ("rf", "frames", "volume", "volumes")


def _npy_volume(path, *, spacing=None, frames=None, **_ignored):
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as fh:
            arr = _parse_npy(fh, size, path, "npy")
    except OSError as exc:
        raise fail(path, f"cannot read ({exc.strerror or exc})") from None
    sp = merge_spacing(path, None, spacing, required_msg=".npy stores no spacing", n=3)
    return finalize_volumes(path, arr, sp, (0.0, 0.0, 0.0), {"format": "npy"}, frames)


def _npz_volume(path, *, variable=None, spacing=None, frames=None, **_ignored):
    arr, raw_sp, raw_origin, key, other = _load_npz(path, variable, VOLUME_KEYS)
    file_spacing = _npz_spacing(path, raw_sp, 3)
    origin = check_origin(raw_origin, path, n=3) if raw_origin is not None else None
    sp = merge_spacing(path, file_spacing, spacing, required_msg="the .npz has no 'spacing' key", n=3)
    return finalize_volumes(path, arr, sp, origin, {"format": "npz", "variable": key, "keys": other}, frames)


def _mat_volume(path, **kw):
    from .matlab import read_mat_volume

    return Volumes(**read_mat_volume(path, **kw))


def _mhd_volume(path, **kw):
    from .metaimage import read_metaimage_volume

    return Volumes(**read_metaimage_volume(path, **kw))


def _check_volume_sampling(vol, spacing) -> None:
    """:func:`femreg.orientation.check_sampling` for volumes: the central axial-lateral plane of the first volume
    as a frame, its header fields and a given ``spacing``'s axial and lateral values (a refusal names the
    volume's elevational value too); notes kept in ``metadata["sampling_notes"]``."""
    from types import SimpleNamespace

    from ..orientation import check_sampling

    a = vol.frames[0]
    plane = SimpleNamespace(frames=[a[:, :, a.shape[2] // 2]], spacing=tuple(vol.spacing[:2]), metadata=vol.metadata)
    notes = check_sampling(plane, None if spacing is None else tuple(spacing)[:2], where=f"{vol.source}: ",
                           elevational=vol.spacing[2],
                           override_as="check_sampling=False (CLI: --no-orientation-check)")   # read_volumes' name
    if notes:
        vol.metadata["sampling_notes"] = notes


_VOLUME_READERS = {"npy": _npy_volume, "npz": _npz_volume, "mat": _mat_volume, "metaimage": _mhd_volume}


def read_volumes(path, *, variable=None, spacing=None, frames=None, check_sampling: bool = True) -> Volumes:
    """Read one RF volume or a sequence of RF volumes from ``path``.

    Parameters
    ----------
    path : str or Path
        ``.npy``, ``.npz``, ``.mat`` or ``.mhd`` / ``.mha`` (module docstring for the layouts).
    variable : str, optional
        Array name in .npz / .mat files (default ``rf``, ``frames``, ``volume``, ``volumes``, else the only
        3D/4D numeric array of a MAT-file).
    spacing : (dx, dy, dz) mm, optional
        Axial, lateral and elevational spacing; overrides the file's (None entries keep the file's); required
        where the file stores none (npy).
    frames : int, slice or sequence of int, optional
        Volume selection (default all).
    check_sampling : bool
        Hold a given axial spacing against the sampling rate the file's fields state, as :func:`read_frames` does
        (:func:`femreg.orientation.check_sampling` on the central axial-lateral plane of the first volume).

    Returns
    -------
    Volumes
        ``frames`` (n, axial, lateral, elevational) float32/float64, finite; ``spacing`` (dx, dy, dz) mm;
        ``origin`` (x0, y0, z0) mm; ``metadata``; ``source``.

    Raises
    ------
    FileFormatError
        Missing, corrupt or truncated file; data that is not 3D/4D; NaN/Inf.
    InputError
        A bad or missing argument (spacing needed but not given, not three values).
    """
    try:
        path = Path(os.fspath(path))
    except TypeError:
        raise InputError(f"path must be a file name, got {path!r}") from None
    if not path.exists():
        raise fail(path, "no such file or directory")
    if spacing is not None:
        from .checks import check_spacing

        check_spacing(spacing, allow_none=True, n=3)
    fmt = "unknown"
    try:
        fmt = detect_format(path)
        if fmt not in _VOLUME_READERS:
            raise InputError(f"{path}: volumes are read from npy, npz, mat and mhd/mha files, not {fmt}")
        if not path.is_file():
            raise fail(path, "not a regular file")
        with open(path, "rb") as fh:
            head = fh.read(8)
        if not head:
            raise fail(path, f"empty file (expected {fmt})")
        _sniff_mislabel(path, head, fmt)
        vol = _VOLUME_READERS[fmt](path, variable=variable, spacing=spacing, frames=frames)
        if check_sampling:
            _check_volume_sampling(vol, spacing)
        return vol
    except (FileFormatError, InputError):
        raise
    except MemoryError:
        raise fail(path, f"not enough memory to read this {fmt} file (corrupt header or too large)") from None
    except Exception as exc:  # never let a library exception escape untyped
        raise fail(path, f"cannot read {fmt} file ({type(exc).__name__}: {exc})") from None
