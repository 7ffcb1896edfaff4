"""A small, defensive reader of MATLAB Level-5 MAT-files (v5/v6/v7) for numeric arrays.

Why not :func:`scipy.io.loadmat`: its compiled v5 reader crashes the interpreter (segmentation fault) on some
corrupted files (found by the property tests in tests/test_io_fuzz.py), and a crash is not a typed error.  This
reader walks the data elements in pure Python/NumPy, checks every size against the bytes available before
touching them, and raises :class:`FileFormatError` otherwise.

Format (MathWorks, "MAT-File Format", Level 5): a 128-byte header (text, subsystem offset, version 0x0100,
endian indicator 'IM'/'MI'), then data elements ``[type u32][nbytes u32][data, padded to 8]`` or the small form
``[nbytes u16 | type u16][4 bytes]``.  A variable is an ``miMATRIX`` element (possibly inside ``miCOMPRESSED``,
zlib) holding array flags (class, complex/logical bits), dimensions, name, real part (and imaginary part), the
data column-major and possibly stored in a smaller integer type than its class.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from ..errors import FileFormatError
from .checks import fail

_MI = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 9: "f8", 12: "i8", 13: "u8"}
MI_MATRIX, MI_COMPRESSED = 14, 15
CLASS_NAMES = {1: "cell", 2: "struct", 3: "object", 4: "char", 5: "sparse", 6: "double", 7: "single", 8: "int8",
               9: "uint8", 10: "int16", 11: "uint16", 12: "int32", 13: "uint32", 14: "int64", 15: "uint64",
               16: "function", 17: "opaque"}
_CLASS_DTYPE = {6: "f8", 7: "f4", 8: "i1", 9: "u1", 10: "i2", 11: "u2", 12: "i4", 13: "u4", 14: "i8", 15: "u8"}
_MAX_ELEMENTS = 1 << 31


@dataclass
class MatVar:
    name: str
    cls: str
    shape: tuple
    numeric: bool
    complex: bool
    _buf: bytes = b""
    _real: tuple = ()
    _imag: tuple = ()
    #: a 1 x 1 struct's numeric fields, nested structs flattened, named by their path in it ("fs", "probe/pitch")
    members: tuple = ()
    #: a char array's text (rows joined by " / "), None for other classes or text that cannot be decoded
    text: str | None = None

    def array(self, order: str) -> np.ndarray:
        """The value in MATLAB index order (float/int dtype of its class; complex if stored so)."""
        mtype, start, n = self._real
        dt = np.dtype(order + _CLASS_DTYPE[_CLASS_INV[self.cls]])
        re = np.frombuffer(self._buf, dtype=order + _MI[mtype], count=n // np.dtype(_MI[mtype]).itemsize,
                           offset=start).astype(dt.newbyteorder("="))
        if self._imag:
            mtype, start, n = self._imag
            im = np.frombuffer(self._buf, dtype=order + _MI[mtype], count=n // np.dtype(_MI[mtype]).itemsize,
                               offset=start)
            re = re + 1j * im
        return re.reshape(self.shape, order="F")


_CLASS_INV = {v: k for k, v in CLASS_NAMES.items()}
#: how deep nested structs are read for their numeric fields
_MAX_STRUCT_DEPTH = 3
#: struct arrays up to this many elements are read for the fields their elements share
_MAX_STRUCT_ELEMENTS = 256


class _Walker:
    def __init__(self, path, order):
        self.path, self.order = path, order
        self.u32 = np.dtype(order + "u4")

    def tag(self, buf, pos, end, where):
        """(type, nbytes, data_start, next_pos) of the element at ``pos``; checks it fits in ``buf[:end]``."""
        if pos + 8 > end:
            raise fail(self.path, f"truncated MAT-file: incomplete data element tag in {where} at byte {pos}")
        w0 = int(np.frombuffer(buf, self.u32, 1, pos)[0])
        if w0 >> 16:  # small data element: nbytes in the upper half, data in the next 4 bytes
            mtype, n = w0 & 0xFFFF, w0 >> 16
            if n > 4:
                raise fail(self.path, f"corrupt MAT-file: small data element of {n} bytes in {where}")
            return mtype, n, pos + 4, pos + 8
        n = int(np.frombuffer(buf, self.u32, 1, pos + 4)[0])
        start = pos + 8
        if start + n > end:
            raise fail(self.path, f"truncated MAT-file: element of {n} bytes at byte {pos} runs past the end "
                                  f"of {where} ({end - start} bytes left)")
        return w0, n, start, start + ((n + 7) // 8) * 8

    def _struct_fields(self, buf, pos, end, where, name, depth, count: int = 1) -> tuple:
        """The numeric fields of a 1 x 1 struct whose field-name length element starts at ``pos`` (MAT-file
        format: name length, names, then one miMATRIX per field), nested ones flattened; exports keep the
        scanner's settings there (``header.fs``, ``P.pitch``).  A struct array of ``count`` elements (Verasonics'
        ``Receive(1:n)``: one per acquisition, element after element) gives the numeric fields every element
        holds alike (``Receive.demodFrequency``), no nested ones.  A layout not understood gives none."""
        if count > 1:
            return self._struct_array_fields(buf, pos, end, where, name, depth, count)
        try:
            names, pos = self._field_names(buf, pos, end, where)
            out = []
            for field in names:
                mtype, n, s, pos = self.tag(buf, pos, end, where)
                if mtype != MI_MATRIX:
                    return tuple(out)
                if not n:
                    continue
                var = self.matrix(buf, s, s + n, f"field {field!r} of {name!r}", depth + 1)
                if var.numeric:
                    var.name = field
                    out.append(var)
                for m in var.members:
                    m.name = f"{field}/{m.name}"
                    out.append(m)
            return tuple(out)
        except FileFormatError:
            return ()

    def _field_names(self, buf, pos, end, where) -> tuple[list, int]:
        """A struct's field names (its name-length and names elements) and the position after them; no names where
        the layout is not understood."""
        mtype, n, s, pos = self.tag(buf, pos, end, where)
        if mtype != 5 or n != 4:
            return [], pos
        width = int(np.frombuffer(buf, self.order + "i4", 1, s)[0])
        mtype, n, s, pos = self.tag(buf, pos, end, where)
        if mtype not in (1, 2) or width <= 0 or n % width:
            return [], pos
        return [bytes(buf[s + k:s + k + width]).split(b"\0")[0].decode("ascii", "replace")
                for k in range(0, n, width)], pos

    def _struct_array_fields(self, buf, pos, end, where, name, depth, count) -> tuple:
        """The numeric fields equal in all ``count`` elements of a struct array (:meth:`_struct_fields`)."""
        try:
            names, pos = self._field_names(buf, pos, end, where)
            values = {field: [] for field in names}
            for _ in range(count):
                for field in names:
                    mtype, n, s, pos = self.tag(buf, pos, end, where)
                    if mtype != MI_MATRIX:
                        return ()
                    var = self.matrix(buf, s, s + n, f"field {field!r} of {name!r}", _MAX_STRUCT_DEPTH) if n \
                        else None
                    values[field].append(var if var is not None and var.numeric else None)
            out = []
            for field, vs in values.items():
                if any(v is None for v in vs):
                    continue
                first = vs[0].array(self.order)
                if all(v.shape == vs[0].shape and np.array_equal(v.array(self.order), first) for v in vs[1:]):
                    vs[0].name = field
                    out.append(vs[0])
            return tuple(out)
        except FileFormatError:
            return ()

    def _text(self, buf, pos, end, where, dims):
        """A char array's characters (stored column-major as miUINT16, miUTF8/16/32 or bytes), its rows joined by
        " / "; None where the element does not hold that many characters (the listing is a courtesy)."""
        try:
            mtype, n, s, _ = self.tag(buf, pos, end, where)
        except FileFormatError:
            return None
        raw = bytes(buf[s:s + n])
        try:
            if mtype in (3, 4):
                chars = [chr(c) for c in np.frombuffer(raw, self.order + "u2")]
            elif mtype in (1, 2):
                chars = list(raw.decode("latin-1"))
            elif mtype in (16, 17, 18):
                enc = {16: "utf-8", 17: "utf-16-le" if self.order == "<" else "utf-16-be",
                       18: "utf-32-le" if self.order == "<" else "utf-32-be"}[mtype]
                chars = list(raw.decode(enc))
            else:
                return None
        except (UnicodeDecodeError, ValueError):
            return None
        if len(dims) != 2 or len(chars) != dims[0] * dims[1]:
            return None
        rows = np.array(chars, dtype=object).reshape(dims, order="F") if chars else np.empty(dims, object)
        return " / ".join("".join(r) for r in rows)

    def matrix(self, buf, start, end, where, depth: int = 0) -> MatVar:
        mtype, n, s, pos = self.tag(buf, start, end, where)
        if mtype != 6 or n != 8:
            raise fail(self.path, f"corrupt MAT-file: bad array flags element in {where}")
        flags = int(np.frombuffer(buf, self.u32, 1, s)[0])
        cls_id, is_complex = flags & 0xFF, bool(flags & 0x0800)
        cls = CLASS_NAMES.get(cls_id)
        if cls is None:
            raise fail(self.path, f"corrupt MAT-file: unknown array class {cls_id} in {where}")
        mtype, n, s, pos = self.tag(buf, pos, end, where)
        if mtype != 5 or n % 4 or n < 8:
            raise fail(self.path, f"corrupt MAT-file: bad dimensions element in {where}")
        dims = tuple(int(d) for d in np.frombuffer(buf, self.order + "i4", n // 4, s))
        if min(dims) < 0 or np.prod(dims, dtype=float) > _MAX_ELEMENTS:
            raise fail(self.path, f"corrupt MAT-file: bad dimensions {dims} in {where}")
        mtype, n, s, pos = self.tag(buf, pos, end, where)
        if mtype not in (1, 2, 16):
            raise fail(self.path, f"corrupt MAT-file: bad array name element in {where}")
        try:
            name = bytes(buf[s:s + n]).decode("ascii")
        except UnicodeDecodeError:
            raise fail(self.path, f"corrupt MAT-file: non-ASCII variable name in {where}") from None
        numeric = cls_id in _CLASS_DTYPE
        var = MatVar(name, cls, dims, numeric, is_complex, buf)
        if cls == "struct" and 1 <= int(np.prod(dims)) <= _MAX_STRUCT_ELEMENTS and depth < _MAX_STRUCT_DEPTH:
            var.members = self._struct_fields(buf, pos, end, where, name, depth, int(np.prod(dims)))
        if cls == "char":
            var.text = self._text(buf, pos, end, where, dims)
        if not numeric:
            return var
        count = int(np.prod(dims))
        parts = []
        for part in ("real", "imaginary")[: 1 + is_complex]:
            mtype, n, s, pos = self.tag(buf, pos, end, where)
            if mtype not in _MI:
                raise fail(self.path, f"corrupt MAT-file: {part} part of {name!r} has data type {mtype}")
            isz = np.dtype(_MI[mtype]).itemsize
            if n != count * isz:
                raise fail(self.path, f"corrupt MAT-file: {part} part of {name!r} holds {n} bytes, "
                                      f"{dims} {_MI[mtype]} needs {count * isz}")
            parts.append((mtype, s, n))
        var._real = parts[0]
        var._imag = parts[1] if is_complex else ()
        return var


def shown_text(text: str, limit: int = 40) -> str:
    """A text variable as a listing shows it: quoted, cut to ``limit`` characters with an ellipsis."""
    text = " ".join(str(text).split())
    return repr(text if len(text) <= limit else text[:limit - 3] + "...")


def read_mat5(path, blob: bytes):
    """All variables of a Level-5 MAT-file as (byte order, list of :class:`MatVar`)."""
    if len(blob) < 128:
        raise fail(path, f"truncated MAT-file: {len(blob)} bytes, the header alone is 128")
    endian = blob[126:128]
    order = {b"IM": "<", b"MI": ">"}.get(endian)
    if order is None:
        raise fail(path, f"bad MAT-file header: endian indicator {endian!r}")
    w = _Walker(path, order)
    out, pos, end = [], 128, len(blob)
    while pos < end:
        mtype, n, s, nxt = w.tag(blob, pos, end, "the file")
        where = f"element at byte {pos}"
        if mtype == MI_COMPRESSED:
            nxt = s + n  # compressed elements are not padded
            d = zlib.decompressobj()
            try:
                inner = d.decompress(blob[s:s + n], 1100 * n + (1 << 20))  # zlib's ratio is at most ~1030
            except zlib.error as exc:
                raise fail(path, f"corrupt compressed MAT-file data ({exc}) in {where}") from None
            if not d.eof or d.unconsumed_tail:
                raise fail(path, f"truncated or corrupt compressed MAT-file data in {where}")
            imt, inn, ins, _ = w.tag(inner, 0, len(inner), where)
            if imt == MI_MATRIX and inn:
                out.append(w.matrix(inner, ins, ins + inn, where))
        elif mtype == MI_MATRIX:
            nxt = s + n
            if n:
                out.append(w.matrix(blob, s, s + n, where))
        elif mtype not in _MI and mtype not in (16, 17, 18):
            raise fail(path, f"corrupt MAT-file: unknown data element type {mtype} at byte {pos}")
        pos = nxt
    return order, out
