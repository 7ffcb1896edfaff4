"""MetaImage (.mhd header + .raw data, or single-file .mha) reader and writer.

Axis mapping
------------
MetaImage stores x fastest: ``DimSize = nx ny [nz]`` and the data file is ``nz`` blocks of ``ny`` rows of ``nx``
samples.  For ultrasound RF the scanner writes one scan line as a column, so MetaImage x is *lateral* (the line
index) and y is *axial* (the sample index along the line); z, when present, is the frame.  The C-order array
``data.reshape(DimSize[::-1])`` is therefore ``(frames, axial, lateral)``, exactly our layout, and
``spacing = (ElementSpacing[1], ElementSpacing[0])``, ``origin = (Offset[1], Offset[0])``.
Check against ../shared/data/invivo_rf: ``np.fromfile(f, "<f4").reshape(2000, 128)`` (2000 axial x 128 lines)
is ``DimSize = 128 2000`` with ``ElementSpacing = 0.2 0.02``.
"""
from __future__ import annotations

import os
import zlib
from pathlib import Path

import numpy as np

from ..errors import InputError
from .checks import fail, merge_spacing, validate_frames, validate_volumes

ELEMENT_TYPES = {
    "MET_CHAR": "i1", "MET_UCHAR": "u1", "MET_SHORT": "i2", "MET_USHORT": "u2",
    "MET_INT": "i4", "MET_UINT": "u4", "MET_LONG": "i4", "MET_ULONG": "u4",
    "MET_LONG_LONG": "i8", "MET_ULONG_LONG": "u8", "MET_FLOAT": "f4", "MET_DOUBLE": "f8",
}
_DTYPE_TO_MET = {np.dtype(v).str[1:]: k for k, v in ELEMENT_TYPES.items() if k not in ("MET_LONG", "MET_ULONG")}

_MAX_HEADER = 1 << 16
_KNOWN_FIRST = {"objecttype", "ndims", "comment", "objectsubtype", "transformtype", "name", "id", "parentid",
                "binarydata", "elementbyteordermsb", "binarydatabyteordermsb", "dimsize", "elementtype",
                "headersize", "elementspacing", "elementsize", "offset", "origin", "position",
                "compresseddata", "transformmatrix", "rotation", "orientation", "centerofrotation",
                "anatomicalorientation", "elementnumberofchannels", "elementdatafile", "modality", "color",
                "elementmin", "elementmax", "acquisitiondate", "sequenceid", "elementsmissing"}


def _parse_header(path: Path):
    """Return (fields dict with lower-case keys -> str, original keys, byte offset just after the header)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(_MAX_HEADER)
    except OSError as exc:
        raise fail(path, f"cannot read ({exc.strerror or exc})") from None
    if not head:
        raise fail(path, "empty file, not a MetaImage header")
    fields, keys, pos = {}, {}, 0
    while pos < len(head):
        end = head.find(b"\n", pos)
        line_end = len(head) if end < 0 else end + 1
        raw = head[pos:(len(head) if end < 0 else end)]
        pos = line_end
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            line = "\0"
        if any(ord(ch) < 32 and ch not in "\t\r" for ch in line):
            raise fail(path, f"MetaImage header has non-text bytes in line {len(fields) + 1}")
        if not line:
            continue
        if "=" not in line:
            raise fail(path, f"bad MetaImage header line {line[:40]!r} (expected 'Key = Value')")
        key, value = (s.strip() for s in line.split("=", 1))
        low = key.lower()
        if not fields and low not in _KNOWN_FIRST:
            raise fail(path, f"not a MetaImage header (first key {key[:40]!r})")
        fields[low] = value
        keys[low] = key
        if low == "elementdatafile":
            return fields, keys, pos
    raise fail(path, "MetaImage header has no ElementDataFile line (truncated or not a header)")


_CANON = {k.lower(): k for k in (
    "ObjectType", "NDims", "DimSize", "ElementType", "ElementSpacing", "ElementSize", "Offset", "Origin", "Position",
    "HeaderSize", "ElementDataFile", "ElementByteOrderMSB", "BinaryDataByteOrderMSB", "CompressedData",
    "ElementNumberOfChannels")}


def _name(key):
    return _CANON.get(key, key)


def _ints(path, fields, key, n=None):
    try:
        vals = [int(v) for v in fields[key].split()]
    except ValueError:
        raise fail(path, f"bad header field {_name(key)}: {fields[key][:40]!r} (expected integers)") from None
    if n is not None and len(vals) != n:
        raise fail(path, f"bad header field {_name(key)}: {len(vals)} value(s), expected {n}")
    return vals


def _floats(path, fields, key, n):
    try:
        vals = [float(v) for v in fields[key].split()]
    except ValueError:
        raise fail(path, f"bad header field {_name(key)}: {fields[key][:40]!r} (expected numbers)") from None
    if len(vals) < n:
        raise fail(path, f"bad header field {_name(key)}: {len(vals)} value(s), expected {n}")
    if not np.all(np.isfinite(vals)):
        raise fail(path, f"bad header field {_name(key)}: non-finite value {fields[key]!r}")
    return vals[:n]


def _bool(path, fields, key):
    v = fields.get(key, "False").strip().lower()
    if v in ("true", "1", "yes"):
        return True
    if v in ("false", "0", "no", ""):
        return False
    raise fail(path, f"bad header field {_name(key)}: {fields[key][:40]!r} (expected True/False)")


def _data_files(path: Path, fields, value: str, header_end: int, ndims: int, dims):
    """List of data files (or [None] for LOCAL) from ElementDataFile."""
    base = path.parent
    if value.upper() == "LOCAL":
        return [None]
    if value.upper().startswith("LIST"):
        with open(path, "rb") as fh:
            fh.seek(header_end)
            try:
                names = fh.read(_MAX_HEADER).decode("ascii").split()
            except UnicodeDecodeError:
                raise fail(path, "ElementDataFile LIST: file names are not text") from None
        if not names:
            raise fail(path, "ElementDataFile LIST names no file")
        return [base / n for n in names]
    parts = value.split()
    if "%" in value and len(parts) >= 3:
        # pattern form: "name%d.raw min max [step]"
        try:
            lo, hi = int(parts[1]), int(parts[2])
            step = int(parts[3]) if len(parts) > 3 else 1
        except ValueError:
            raise fail(path, f"bad ElementDataFile pattern {value!r}") from None
        if step == 0 or abs(hi - lo) // abs(step) > 100000:
            raise fail(path, f"bad ElementDataFile pattern range {value!r}")
        try:
            return [base / (parts[0] % i) for i in range(lo, hi + (1 if step > 0 else -1), step)]
        except (TypeError, ValueError):
            raise fail(path, f"bad ElementDataFile pattern {value!r}") from None
    return [base / value]


def _load(path, allowed=(2, 3)):
    """(C-order array ``data.reshape(DimSize[::-1])``, NDims, header fields, original keys, msb, ElementType)."""
    fields, keys, header_end = _parse_header(path)
    for req in ("ndims", "dimsize", "elementtype"):
        if req not in fields:
            raise fail(path, f"MetaImage header lacks the {_name(req)} field")
    (ndims,) = _ints(path, fields, "ndims", 1)
    if ndims not in allowed:
        hint = ""
        if ndims == 4 and 4 not in allowed:
            hint = "; a 4D image is a volume sequence: read it with femreg.io.read_volumes"
        raise fail(path, f"bad header field NDims = {ndims} (need {' or '.join(map(str, allowed))}){hint}")
    dims = _ints(path, fields, "dimsize", ndims)
    if min(dims) < 1:
        raise fail(path, f"bad header field DimSize = {dims} (must be positive)")
    etype = fields["elementtype"].upper()
    if etype not in ELEMENT_TYPES:
        raise fail(path, f"unknown ElementType {fields['elementtype'][:40]!r}; known: "
                         + ", ".join(sorted(ELEMENT_TYPES)))
    channels = _ints(path, fields, "elementnumberofchannels", 1)[0] if "elementnumberofchannels" in fields else 1
    if channels != 1:
        raise fail(path, f"ElementNumberOfChannels = {channels}: only scalar images are RF frames")
    msb = _bool(path, fields, "elementbyteordermsb") or _bool(path, fields, "binarydatabyteordermsb")
    dtype = np.dtype(ELEMENT_TYPES[etype]).newbyteorder(">" if msb else "<")
    count = int(np.prod(dims, dtype=np.int64))
    nbytes = count * dtype.itemsize
    compressed = _bool(path, fields, "compresseddata")
    header_size = _ints(path, fields, "headersize", 1)[0] if "headersize" in fields else 0
    if header_size < -1:
        raise fail(path, f"bad header field HeaderSize = {header_size}")

    files = _data_files(path, fields, fields["elementdatafile"], header_end, ndims, dims)
    if len(files) > 1 and dims[-1] % len(files):
        raise fail(path, f"{len(files)} data files do not divide DimSize {dims}")
    chunk = nbytes // len(files)
    pieces = []
    for f in files:
        data_path = path if f is None else f
        start = header_end if f is None else 0
        try:
            size = os.path.getsize(data_path)
            with open(data_path, "rb") as fh:
                if compressed:
                    fh.seek(start)
                    blob = fh.read()
                    try:
                        blob = zlib.decompressobj().decompress(blob, chunk + 1)
                    except zlib.error as exc:
                        raise fail(data_path, f"corrupt compressed MetaImage data ({exc})") from None
                    if len(blob) != chunk:
                        raise fail(data_path, f"compressed data holds {len(blob)} bytes, header needs {chunk}")
                else:
                    if f is not None and header_size == -1:
                        start = size - chunk
                    elif f is not None:
                        start = header_size
                    avail = size - start
                    if start < 0 or avail < chunk:
                        raise fail(data_path, f"truncated MetaImage data: {max(avail, 0)} bytes after offset "
                                              f"{max(start, 0)}, header DimSize {dims} {etype} needs {chunk}")
                    fh.seek(start)
                    blob = fh.read(chunk)
        except FileNotFoundError:
            raise fail(path, f"ElementDataFile {str(data_path)!r} not found") from None
        except IsADirectoryError:
            raise fail(path, f"ElementDataFile {str(data_path)!r} is a directory") from None
        except OSError as exc:
            raise fail(data_path, f"cannot read ({exc.strerror or exc})") from None
        pieces.append(blob)
    arr = np.frombuffer(b"".join(pieces), dtype=dtype).reshape(dims[::-1])

    return arr, ndims, fields, keys, msb, etype, dtype


def read_metaimage(path, *, spacing=None, frames=None, **_ignored):
    """Read a MetaImage ``.mhd``/``.mha`` file: the fields of a :class:`~femreg.io.Frames` (module docstring)."""
    path = Path(path)
    arr, ndims, fields, keys, msb, etype, dtype = _load(path)
    file_spacing = None
    for key in ("elementspacing", "elementsize"):
        if key in fields:
            sp = _floats(path, fields, key, ndims)
            file_spacing = (sp[1], sp[0])
            break
    origin = (0.0, 0.0)
    for key in ("offset", "origin", "position"):
        if key in fields:
            o = _floats(path, fields, key, ndims)
            origin = (o[1], o[0])
            break
    sp = merge_spacing(path, file_spacing, spacing, required_msg="the header has no ElementSpacing")
    meta = {"format": "metaimage", "header": {keys[k]: v for k, v in fields.items()},
            "element_type": etype, "byte_order": "big" if msb else "little", "dtype": str(dtype.newbyteorder("="))}
    return validate_frames(path, arr, sp, origin, meta, frames)


def read_metaimage_volume(path, *, spacing=None, frames=None, **_ignored):
    """Read a MetaImage volume (NDims 3) or volume sequence (NDims 4): the fields of a
    :class:`~femreg.io.Volumes`.

    The 2D mapping extended by elevation: MetaImage x = lateral, y = axial, z = elevational, the fourth axis
    (if any) the frame; so the C-order array ``(frames, elevational, axial, lateral)`` is transposed to
    ``(frames, axial, lateral, elevational)``, ``spacing = (ElementSpacing[1], ElementSpacing[0],
    ElementSpacing[2])`` and the origin likewise.
    """
    path = Path(path)
    arr, ndims, fields, keys, msb, etype, dtype = _load(path, allowed=(3, 4))
    arr = arr[None] if ndims == 3 else arr
    arr = arr.transpose(0, 2, 3, 1)
    file_spacing = None
    for key in ("elementspacing", "elementsize"):
        if key in fields:
            sp = _floats(path, fields, key, 3)
            file_spacing = (sp[1], sp[0], sp[2])
            break
    origin = (0.0, 0.0, 0.0)
    for key in ("offset", "origin", "position"):
        if key in fields:
            o = _floats(path, fields, key, 3)
            origin = (o[1], o[0], o[2])
            break
    sp = merge_spacing(path, file_spacing, spacing, required_msg="the header has no ElementSpacing", n=3)
    meta = {"format": "metaimage", "header": {keys[k]: v for k, v in fields.items()},
            "element_type": etype, "byte_order": "big" if msb else "little", "dtype": str(dtype.newbyteorder("="))}
    return validate_volumes(path, arr, sp, origin, meta, frames)


def write_metaimage_volume(path, volumes: np.ndarray, spacing, origin=(0.0, 0.0, 0.0), *, dtype=None,
                           byte_order="little"):
    """Write a volume (axial, lateral, elevational) or volume sequence (n, axial, lateral, elevational) as
    MetaImage NDims 3 / 4 with the axis mapping of :func:`read_metaimage_volume`; returns the files written."""
    arr = np.asarray(volumes)
    if arr.ndim not in (3, 4):
        raise InputError(f"volumes must be 3D or 4D, got shape {arr.shape}")
    one = arr.ndim == 3
    a4 = arr[None] if one else arr
    c_order = np.ascontiguousarray(a4.transpose(0, 3, 1, 2))        # (n, elevational, axial, lateral)
    dx, dy, dz = (float(v) for v in spacing)
    x0, y0, z0 = (float(v) for v in origin)
    return _write(path, c_order[0] if one else c_order, [dy, dx, dz] + ([] if one else [1.0]),
                  [y0, x0, z0] + ([] if one else [0.0]), dtype=dtype, byte_order=byte_order)


def write_metaimage(path, frames: np.ndarray, spacing, origin=(0.0, 0.0), *, dtype=None, byte_order="little",
                    local=None, data_file=None):
    """Write ``frames`` ((axial, lateral) or (n, axial, lateral)) as MetaImage.

    ``path`` ending in ``.mha`` (or ``local=True``) writes one file with ``ElementDataFile = LOCAL``; otherwise a
    ``.mhd`` header and a data file (default: same stem, ``.raw``) next to it.  Returns the list of files written.
    """
    arr = np.asarray(frames)
    if arr.ndim not in (2, 3):
        raise InputError(f"frames must be 2D or 3D, got shape {arr.shape}")
    sp = [float(spacing[1]), float(spacing[0])] + ([1.0] if arr.ndim == 3 else [])
    off = [float(origin[1]), float(origin[0])] + ([0.0] if arr.ndim == 3 else [])
    return _write(path, arr, sp, off, dtype=dtype, byte_order=byte_order, local=local, data_file=data_file)


def _write(path, arr, sp, off, *, dtype=None, byte_order="little", local=None, data_file=None):
    """Header + data of the C-order array ``arr`` (MetaImage x fastest), spacing/offset in MetaImage order."""
    path = Path(path)
    dt = np.dtype(dtype if dtype is not None else (arr.dtype if arr.dtype.kind in "iuf" else np.float32))
    key = dt.newbyteorder("<").str[1:]
    if key not in _DTYPE_TO_MET:
        raise InputError(f"dtype {dt} has no MetaImage ElementType")
    if byte_order not in ("little", "big"):
        raise InputError(f"byte_order must be 'little' or 'big', got {byte_order!r}")
    dt = dt.newbyteorder("<" if byte_order == "little" else ">")
    local = path.suffix.lower() == ".mha" if local is None else local
    dims = list(arr.shape[::-1])  # x (lateral) fastest
    msb = "True" if byte_order == "big" else "False"
    data_path = None if local else (Path(data_file) if data_file else path.with_suffix(".raw"))
    header = [
        "ObjectType = Image",
        f"NDims = {arr.ndim}",
        "BinaryData = True",
        f"BinaryDataByteOrderMSB = {msb}",
        "CompressedData = False",
        f"Offset = {' '.join(repr(v) for v in off)}",
        f"ElementSpacing = {' '.join(repr(v) for v in sp)}",
        f"DimSize = {' '.join(str(d) for d in dims)}",
        f"ElementType = {_DTYPE_TO_MET[key]}",
        f"ElementDataFile = {'LOCAL' if local else os.path.relpath(data_path, path.parent)}",
    ]
    blob = np.ascontiguousarray(arr, dtype=dt).tobytes()
    text = ("\n".join(header) + "\n").encode("ascii")
    if local:
        path.write_bytes(text + blob)
        return [path]
    path.write_bytes(text)
    data_path.write_bytes(blob)
    return [path, data_path]
