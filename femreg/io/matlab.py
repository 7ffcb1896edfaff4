"""MATLAB ``.mat`` files: v5/v7 by :mod:`femreg.io.mat5` (pure Python; scipy's compiled reader can crash on
corrupt files), v4 by :func:`scipy.io.loadmat`, v7.3 (HDF5) by h5py.

Layout: MATLAB users keep a sequence as ``rf(axial, lateral, frame)`` (frames on the *last* axis), which is
how both readers return a 3D variable in MATLAB index order; it is moved to our ``(n, axial, lateral)``.
A v7.3 file stores every array transposed (HDF5 is row-major, MATLAB column-major): the HDF5 dataset of
``rf(axial, lateral, frame)`` has shape ``(frame, lateral, axial)``; we transpose it back.

Variables: ``variable=`` picks one; otherwise ``rf`` or ``frames`` if present, else the only 2D/3D numeric
variable.  ``spacing`` (two numbers, mm) and ``origin`` variables are used when present.
"""
from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np

from ..errors import InputError, pass_as
from .hdf5 import _as_complex, iq_pair_names
from .checks import (AXIS_MAX, MIN_FRAME_SAMPLES, axis_fields, check_origin, fail, merge_spacing, scalar_fields,
                     spacing_suggestion, validate_frames, validate_volumes)

PREFERRED = ("rf", "frames")
AUX = ("spacing", "origin")
_HDF5_SIG = b"\x89HDF\r\n\x1a\n"
_NUMERIC_CLASSES = {"double", "single", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64",
                    "uint64", "logical"}


def mat_version(path) -> str:
    """'7.3' (HDF5), '5' (v5/v6/v7 Level 5) or '4' from the file's first bytes; FileFormatError otherwise."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(1024 + 8)
    except OSError as exc:
        raise fail(path, f"cannot read ({exc.strerror or exc})") from None
    if len(head) >= 128 and head[:6] == b"MATLAB":
        ver = head[124:126]
        endian = head[126:128]
        if endian == b"IM":
            ver = ver[::-1]
        elif endian != b"MI":
            raise fail(path, f"bad MAT-file header: endian indicator {endian!r}")
        if ver == b"\x02\x00":
            if head[512:520] != _HDF5_SIG:
                raise fail(path, "MAT-file v7.3 header but no HDF5 data at byte 512 (truncated or corrupt)")
            return "7.3"
        if ver == b"\x01\x00":
            return "5"
        raise fail(path, f"bad MAT-file header: version bytes {ver!r}")
    for off in (0, 512, 1024):
        if head[off:off + 8] == _HDF5_SIG:
            return "7.3"
    if len(head) >= 20:
        # v4 has no magic: its first int32 is a type code MOPT < 5000 with zero M and O digits
        for order in ("<", ">"):
            mopt, mrows, ncols, imagf, namlen = np.frombuffer(head[:20], dtype=order + "i4")
            if (0 <= mopt < 5000 and (mopt // 100) % 10 == 0 and 0 < mrows and 0 < ncols and imagf in (0, 1)
                    and 0 < namlen < 64):
                return "4"
    raise fail(path, "not a MATLAB MAT-file (no 'MATLAB' header, not HDF5)")


def _listed(names, texts=None) -> str:
    """Variable names for a message, a text variable with its (cut) text: ``a, when = '2026-11-30'``."""
    from .mat5 import shown_text

    texts = texts or {}
    shown = (f"{k} = {shown_text(texts[k])}" if texts.get(k) is not None else k for k in sorted(names))
    return ", ".join(shown) or "none"


def frames_shape(shape) -> tuple:
    """The MATLAB shape of a frames variable as femreg reads it: ``(axial, lateral, 1, frame)`` -- a Verasonics
    ``IData{1}`` / ``ImgData{1}``, whose third axis holds its one section (plane) -- as ``(axial, lateral,
    frame)``; other shapes as they are."""
    shape = tuple(shape)
    return shape[:2] + shape[3:] if len(shape) == 4 and shape[2] == 1 else shape


def _choose(path, candidates: dict, variable, ndims=(2, 3), texts=None, pairs=None):
    """Pick the frames variable among ``{name: (shape, numeric)}`` (the only one with ``ndims`` dimensions);
    ``texts``: ``{name: text}`` of the char variables, shown in the messages that list the variables; ``pairs``:
    ``{in-phase: quadrature}`` of IQ stored as two real variables (one candidate, named by its in-phase half,
    whichever half ``variable`` names)."""
    pairs = pairs or {}
    if variable is not None:
        if variable not in candidates:
            raise fail(path, f"missing variable {variable!r}; available: {_listed(candidates, texts)}")
        return next((i for i, q in pairs.items() if q == variable), variable)
    for name in PREFERRED:
        if name in candidates:
            return name
    quadrature = set(pairs.values())
    if 4 not in ndims:              # frames: a Verasonics (axial, lateral, 1, frame) is one too
        candidates = {k: (frames_shape(shape), numeric) for k, (shape, numeric) in candidates.items()}
    good = [k for k, (shape, numeric) in candidates.items()
            if numeric and len(shape) in ndims and k not in AUX and k not in quadrature and min(shape, default=0) > 1]
    if len(good) == 1:
        return good[0]
    dims = "/".join(f"{d}D" for d in ndims)
    if not good:
        raise fail(path, f"no {dims} numeric variable found (variables: {_listed(candidates, texts)})")
    raise fail(path, f"several {dims} variables ({', '.join(sorted(good))}); choose one with "
                     + pass_as("variable= (CLI: --variable NAME)", "--variable NAME"))


def _mat_layout(arr, meta=None):
    """MATLAB index order (axial, lateral[, frame]) -> (frame, axial, lateral); a stack stored frames first
    (``(frame, axial, lateral)``, as numpy writes it) is recognised by the size of the frames each reading gives
    (:data:`MIN_FRAME_SAMPLES`) and read as such, ``meta["layout"]`` saying so."""
    arr = np.asarray(arr)
    if arr.ndim == 3:
        matlab_frame, first_frame = arr.shape[:2], arr.shape[1:]
        if min(matlab_frame) < MIN_FRAME_SAMPLES <= min(first_frame):
            if meta is not None:
                meta["layout"] = (f"frames first ({arr.shape[0]} frames of {arr.shape[1]} x {arr.shape[2]}): the "
                                  f"MATLAB order (axial, lateral, frame) would give {arr.shape[2]} frames of "
                                  f"{arr.shape[0]} x {arr.shape[1]} samples")
            return arr
        arr = np.moveaxis(arr, -1, 0)
    return arr


def _aux(path, values: dict, spacing, n=2, frame_shape=None, iq=False):
    file_spacing = None
    if "spacing" in values:
        try:
            if np.iscomplexobj(values["spacing"]):
                raise TypeError
            sp = np.asarray(values["spacing"], dtype=float).ravel()
        except (TypeError, ValueError):
            raise fail(path, "variable 'spacing' is not numeric") from None
        if sp.size != n:
            hint = {(2, 3): " (three values: a volume; read it with femreg.io.read_volumes)",
                    (3, 2): " (two values: 2D frames; read them with femreg.io.read_frames)"}.get((n, sp.size), "")
            raise fail(path, f"variable 'spacing' has {sp.size} values, expected {n} "
                             f"{'(dx, dy)' if n == 2 else '(dx, dy, dz)'} mm{hint}")
        file_spacing = tuple(sp)
    origin = check_origin(values["origin"], path, n=n) if "origin" in values else (0.0,) * n
    sp = merge_spacing(path, file_spacing, spacing, n=n, required_msg="no 'spacing' variable in the MAT-file",
                       suggestion=spacing_suggestion(values.get("scalars") or {}, volume=n == 3, iq=iq),
                       frame_shape=frame_shape)
    return sp, origin


def _load_mat(path, variable, ndims):
    """(array in MATLAB index order, aux values, version, variable name, candidates) of any MAT-file version."""
    path = Path(path)
    version = mat_version(path)
    if version == "7.3":
        arr, aux, name, cands = _read_mat73(path, variable, ndims)
        return arr, aux, version, name, cands
    if version == "5":
        from .mat5 import read_mat5

        try:
            blob = path.read_bytes()
        except OSError as exc:
            raise fail(path, f"cannot read ({exc.strerror or exc})") from None
        order, variables = read_mat5(path, blob)
        byname = {v.name: v for v in variables}
        cands = {v.name: (v.shape, v.numeric) for v in variables}
        pairs = iq_pair_names({v.name: (frames_shape(v.shape), v.numeric and not v.complex) for v in variables})
        name = _choose(path, cands, variable, ndims, {v.name: v.text for v in variables}, pairs)
        var = byname[name]
        if not var.numeric:
            raise fail(path, f"variable {name!r} is a MATLAB {var.cls}, not a numeric array")
        data = {name: var.array(order)}
        if name in pairs:       # IQ as two real variables (IData / QData): one complex array
            quad = pairs[name]
            data["stored_dtype"] = f"complex {var.cls} (variables {name!r} + 1j {quad!r})"
            data["iq_variables"] = [name, quad]
            data[name] = _as_complex(data[name], byname[quad].array(order))
        skip = {name, pairs.get(name)}
        for a in AUX:
            if a in byname and a != name and byname[a].numeric:
                data[a] = byname[a].array(order)
        data["scalars"] = {v.name: v.array(order) for v in variables
                           if v.numeric and v.name not in skip and int(np.prod(v.shape)) == 1}
        # a struct's scalars too (an export's header.fs, P.pitch), named by their path: header/fs
        data["scalars"].update({f"{v.name}/{m.name}": m.array(order) for v in variables for m in v.members
                                if int(np.prod(m.shape)) == 1})
        data["vectors"] = {v.name: v.array(order) for v in variables if v.numeric and v.name not in skip
                           and 3 <= int(np.prod(v.shape)) <= AXIS_MAX}
        # a struct's vectors too (an export's header.line_angles): a convex probe's ray angles live there
        data["vectors"].update({f"{v.name}/{m.name}": m.array(order) for v in variables for m in v.members
                                if 3 <= int(np.prod(m.shape)) <= AXIS_MAX})
    else:
        data, cands, name = _read_mat4(path, variable, ndims)
    arr = data.pop(name)
    return arr, {k: v for k, v in data.items() if k in AUX + ("scalars", "vectors", "stored_dtype", "iq_variables")}, \
        version, name, cands


def read_mat(path, *, variable=None, spacing=None, frames=None, **_ignored):
    """Read a MATLAB file (any version): the fields of a :class:`~femreg.io.Frames` (see module docstring)."""
    path = Path(path)
    arr, aux, version, name, cands = _load_mat(path, variable, (2, 3))
    sections = np.ndim(arr) == 4 and np.shape(arr)[2] == 1
    if sections:                    # (axial, lateral, 1, frame): Verasonics' one section dropped
        arr = np.asarray(arr)[:, :, 0, :]
    sp, origin = _aux(path, aux, spacing, frame_shape=_mat_layout(arr).shape[-2:], iq=np.iscomplexobj(arr))
    meta = {"format": f"mat-v{version}", "variable": name, "variables": sorted(cands)}
    if "stored_dtype" in aux:
        meta["stored_dtype"] = aux["stored_dtype"]
    if "iq_variables" in aux:
        meta["iq_variables"] = aux["iq_variables"]
    if sections:
        meta["layout"] = (f"(axial, lateral, 1, frame): {arr.shape[-1]} frames of {arr.shape[0]} x {arr.shape[1]}, "
                          "the one-long third axis (a Verasonics IData / ImgData's section) dropped")
    fields = scalar_fields((aux.get("scalars") or {}).items())
    if fields:
        meta["fields"] = fields
    axes = axis_fields((aux.get("vectors") or {}).items())
    if axes:
        meta["axes"] = axes
    return validate_frames(path, _mat_layout(arr, meta), sp, origin, meta, frames)


def read_mat_volume(path, *, variable=None, spacing=None, frames=None, **_ignored):
    """Read a volume ``rf(axial, lateral, elevational)`` or a volume sequence ``rf(axial, lateral, elevational,
    frame)`` (frames on the last axis, as the 2D layout) from a MAT-file: the fields of a
    :class:`~femreg.io.Volumes`; ``spacing`` three numbers (dx, dy, dz) mm, ``origin`` three."""
    path = Path(path)
    arr, aux, version, name, cands = _load_mat(path, variable, (3, 4))
    sp, origin = _aux(path, aux, spacing, n=3)
    arr = np.asarray(arr)
    if arr.ndim == 4:
        arr = np.moveaxis(arr, -1, 0)
    meta = {"format": f"mat-v{version}", "variable": name, "variables": sorted(cands)}
    fields = scalar_fields((aux.get("scalars") or {}).items())
    if fields:                      # the sampling rate a given spacing is held against (read_volumes)
        meta["fields"] = fields
    return validate_volumes(path, arr, sp, origin, meta, frames)


def _read_mat4(path, variable, ndims=(2, 3)):
    """Level-4 files (no header) through scipy.io's pure-Python v4 reader."""
    import scipy.io

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            info = scipy.io.whosmat(str(path))
            cands = {n: (tuple(shape), cls in _NUMERIC_CLASSES) for n, shape, cls in info}
            name = _choose(path, cands, variable, ndims)
            wanted = [name] + [a for a in AUX if a in cands and a != name]
            data = scipy.io.loadmat(str(path), variable_names=wanted, squeeze_me=False)
    except InputError:
        raise
    except Exception as exc:  # scipy raises MatReadError, ValueError, TypeError, struct errors, ...
        raise fail(path, f"corrupt or truncated MAT-file v4 ({type(exc).__name__}: {exc})") from None
    if name not in data:
        raise fail(path, f"missing variable {name!r} (could not be read)")
    return data, cands, name


def _complex_compound(dtype) -> bool:
    """MATLAB v7.3's layout of a complex array: a compound of numeric 'real' and 'imag' fields."""
    names = dtype.names or ()
    return set(names) == {"real", "imag"} and all(dtype[k].kind in "iuf" for k in names)


def text73(ds):
    """A v7.3 char dataset's text (MATLAB writes it as uint16 codes, transposed): rows joined by " / "."""
    codes = np.asarray(ds[()]).T
    try:
        return " / ".join("".join(chr(int(c)) for c in row) for row in codes)
    except (ValueError, OverflowError):
        return None


def _struct_members73(f, depth: int = 3):
    """(path, dataset) of the numeric fields of a v7.3 file's scalar structs, nested ``depth`` levels at most: a
    struct is an HDF5 group, its fields datasets or groups (``P/Trans/radiusMm``); struct arrays and cells hold
    object references instead and are left out."""
    import h5py

    out = []

    def walk(group, prefix, level):
        for key in group.keys():
            obj = group.get(key)
            if isinstance(obj, h5py.Group):
                if level < depth:
                    walk(obj, f"{prefix}{key}/", level + 1)
                continue
            if not isinstance(obj, h5py.Dataset) or obj.dtype.kind not in "biuf" or obj.dtype.names:
                continue
            cls = obj.attrs.get("MATLAB_class", b"double")
            cls = cls.decode("ascii", "replace") if isinstance(cls, bytes) else str(cls)
            if cls in _NUMERIC_CLASSES and "MATLAB_empty" not in obj.attrs:
                out.append((f"{prefix}{key}", obj))

    for key in f.keys():
        obj = f.get(key)
        if not key.startswith("#") and isinstance(obj, h5py.Group):
            walk(obj, f"{key}/", 1)
    return out


def _read_mat73(path, variable, ndims=(2, 3)):
    import h5py

    try:
        with h5py.File(path, "r") as f:
            cands, dsets, texts = {}, {}, {}
            for key in f.keys():
                if key.startswith("#"):
                    continue
                obj = f.get(key)
                if not isinstance(obj, h5py.Dataset):
                    cands[key] = ((), False)  # struct / cell / object
                    continue
                cls = obj.attrs.get("MATLAB_class", b"double")
                cls = cls.decode("ascii", "replace") if isinstance(cls, bytes) else str(cls)
                empty = "MATLAB_empty" in obj.attrs and bool(np.any(obj.attrs["MATLAB_empty"]))
                numeric = (cls in _NUMERIC_CLASSES and (obj.dtype.kind in "biuf" or _complex_compound(obj.dtype))
                           and not empty)
                cands[key] = (tuple(obj.shape[::-1]), numeric)
                dsets[key] = obj
                if cls == "char" and obj.dtype.kind in "iu" and obj.ndim == 2 and obj.size <= 4096:
                    texts[key] = text73(obj)
            pairs = iq_pair_names({k: (frames_shape(cands[k][0]), cands[k][1] and d.dtype.kind in "iuf"
                                       and not d.dtype.names)
                                   for k, d in dsets.items()})
            name = _choose(path, cands, variable, ndims, texts, pairs)
            if name not in dsets or not cands[name][1]:
                ds = dsets.get(name)
                what = "a struct/cell" if ds is None else (f"compound {ds.dtype}" if ds.dtype.names
                                                            else f"class {ds.attrs.get('MATLAB_class', '?')!r}")
                raise fail(path, f"variable {name!r} is not a numeric array ({what})")
            ds = dsets[name]
            if ds.size * ds.dtype.itemsize > 1 << 34:
                raise fail(path, f"variable {name!r} claims {ds.shape} {ds.dtype} (over 16 GiB)")
            arr = ds[()].T  # HDF5 row-major copy of a column-major MATLAB array
            stored = None
            if arr.dtype.names:   # MATLAB's complex arrays: a compound of 'real' and 'imag'
                stored = f"complex {arr.dtype['real'].name}"
                ctype = np.complex128 if arr.dtype["real"].itemsize == 8 else np.complex64
                arr = arr["real"].astype(ctype) + 1j * arr["imag"].astype(ctype)
            elif name in pairs:     # IQ as two real variables (IData / QData): one complex array
                quad = pairs[name]
                cls = ds.attrs.get("MATLAB_class", b"double")
                cls = cls.decode("ascii", "replace") if isinstance(cls, bytes) else str(cls)
                stored = f"complex {cls} (variables {name!r} + 1j {quad!r})"
                arr = _as_complex(arr, dsets[quad][()].T)
            skip = {name, pairs.get(name)}
            aux = {"scalars": {k: d[()] for k, d in dsets.items() if k not in skip and cands[k][1] and d.size == 1
                               and not d.dtype.names},
                   "vectors": {k: d[()] for k, d in dsets.items() if k not in skip and cands[k][1]
                               and 3 <= d.size <= AXIS_MAX and not d.dtype.names}}
            # a struct's numbers too (P.fs, P.Trans.radiusMm), named by their path as the v5 reader names them
            for key, d in _struct_members73(f):
                if d.size == 1:
                    aux["scalars"][key] = d[()]
                elif 3 <= d.size <= AXIS_MAX:
                    aux["vectors"][key] = d[()]
            for a in AUX:
                if a in dsets and a != name and cands[a][1]:
                    aux[a] = dsets[a][()]
            if stored:
                aux["stored_dtype"] = stored
            if name in pairs:
                aux["iq_variables"] = [name, pairs[name]]
    except InputError:
        raise
    except Exception as exc:  # h5py raises OSError, KeyError, ValueError, RuntimeError on corrupt files
        raise fail(path, f"corrupt or truncated MAT-file v7.3 / HDF5 ({type(exc).__name__}: {exc})") from None
    return arr, aux, name, cands


# ------------------------------------------------------------------------------------------------- writers

def _to_matlab(frames):
    arr = np.asarray(frames)
    if arr.ndim == 3:
        arr = np.moveaxis(arr, 0, -1)  # (n, axial, lateral) -> rf(axial, lateral, frame)
    return arr


def write_mat(path, frames, spacing=None, origin=(0.0, 0.0), *, variable="rf", version="5"):
    """Write frames as a MATLAB file holding ``variable`` (MATLAB order ``(axial, lateral, frame)``),
    ``spacing`` and ``origin``.  ``version`` '5' uses scipy.io.savemat, '7.3' writes an HDF5 file with the
    512-byte MATLAB header, transposed datasets and ``MATLAB_class`` attributes (what MATLAB's ``save -v7.3``
    produces, so MATLAB's ``load`` reads it)."""
    return _write_vars(path, _to_matlab(frames), variable, spacing, origin, 2, version)


def _write_vars(path, arr, variable, spacing, origin, n, version):
    path = Path(path)
    data = {variable: arr}
    if spacing is not None:
        data["spacing"] = np.asarray(spacing, dtype=float).reshape(1, n)
    if origin is not None:
        data["origin"] = np.asarray(origin, dtype=float).reshape(1, n)
    if str(version) in ("5", "7"):
        import scipy.io

        scipy.io.savemat(str(path), data, do_compression=str(version) == "7")
        return [path]
    if str(version) != "7.3":
        raise InputError(f"MAT-file version must be '5', '7' or '7.3', got {version!r}")
    import h5py

    classes = {"f8": "double", "f4": "single", "i1": "int8", "u1": "uint8", "i2": "int16", "u2": "uint16",
               "i4": "int32", "u4": "uint32", "i8": "int64", "u8": "uint64"}
    with h5py.File(path, "w", userblock_size=512) as f:
        for key, val in data.items():
            val = np.asarray(val)
            if val.ndim < 2:
                val = val.reshape(1, -1)
            cls = classes.get(val.dtype.str[1:])
            if cls is None:
                raise InputError(f"cannot store dtype {val.dtype} in a MAT-file")
            ds = f.create_dataset(key, data=np.ascontiguousarray(val.T))
            ds.attrs["MATLAB_class"] = np.bytes_(cls)
    stamp = time.strftime("%a %b %d %H:%M:%S %Y", time.gmtime())
    text = f"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: {stamp} HDF5 schema 1.00 .".encode("ascii")
    head = text.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM"
    with open(path, "r+b") as fh:
        fh.write(head.ljust(512, b"\x00"))
    return [path]


def write_mat_volume(path, volumes, spacing=None, origin=(0.0, 0.0, 0.0), *, variable="rf", version="5"):
    """Write a volume or volume sequence in the MATLAB order of :func:`read_mat_volume`
    (``rf(axial, lateral, elevational[, frame])``) with 1 x 3 ``spacing`` and ``origin``."""
    arr = np.asarray(volumes)
    if arr.ndim not in (3, 4):
        raise InputError(f"volumes must be 3D or 4D, got shape {arr.shape}")
    if arr.ndim == 4:
        arr = np.moveaxis(arr, 0, -1)
    return _write_vars(path, arr, variable, spacing, origin, 3, version)
