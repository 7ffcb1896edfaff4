"""Ultrasonix ``.rf`` files (RF frames from Ultrasonix / Analogic SonixRP/Touch research interfaces).

Layout
------
A 76-byte header of 19 little-endian int32 (``uFileHeader``)::

    type, frames, w, h, ss, ul.x, ul.y, ur.x, ur.y, br.x, br.y, bl.x, bl.y, probe, txf, sf, dr, ld, extra

``type`` 16 is RF data: each frame holds ``w`` scan lines of ``h`` int16 samples (``ss`` = 16 bits per
sample), column-major, i.e. line after line.  Some software versions prefix each frame with a 4-byte frame
number ("frame tag"); whether they are present is decided from the file size, which must match one of
``76 + frames*w*h*2`` or ``76 + frames*(4 + w*h*2)`` exactly.

Spacing: axial ``dx = c / (2 sf)`` with ``c`` = 1540 m/s unless given (``sf`` in Hz); the lateral line pitch
is not in the file and must be given.
"""
from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from ..errors import InputError
from .checks import check_spacing, fail, merge_spacing, select_frames, spacing_suggestion, validate_frames

HEADER_FIELDS = ("type", "frames", "w", "h", "ss", "ul_x", "ul_y", "ur_x", "ur_y", "br_x", "br_y",
                 "bl_x", "bl_y", "probe", "txf", "sf", "dr", "ld", "extra")
HEADER_SIZE = 4 * len(HEADER_FIELDS)  # 76
RF_TYPE = 16
_STRUCT = struct.Struct("<19i")
SOUND_SPEED = 1540.0  # m/s


def read_header(path) -> dict:
    """Parse and check the 76-byte header; returns the fields by name (see :data:`HEADER_FIELDS`)."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(HEADER_SIZE)
    except OSError as exc:
        raise fail(path, f"cannot read ({exc.strerror or exc})") from None
    if len(raw) < HEADER_SIZE:
        raise fail(path, f"truncated Ultrasonix header: {len(raw)} of {HEADER_SIZE} bytes")
    hdr = dict(zip(HEADER_FIELDS, _STRUCT.unpack(raw)))
    if hdr["type"] != RF_TYPE:
        raise fail(path, f"bad header field type = {hdr['type']}: only RF data (type {RF_TYPE}) is supported")
    if hdr["ss"] != 16:
        raise fail(path, f"bad header field ss (sample size) = {hdr['ss']} bits; RF data is 16-bit")
    for name in ("frames", "w", "h"):
        if not 0 < hdr[name] <= 1 << 20:
            raise fail(path, f"bad header field {name} = {hdr[name]}")
    return hdr


def read_ultrasonix(path, *, spacing=None, frames=None, sound_speed=None, **_ignored):
    """Read an Ultrasonix RF file: the fields of a :class:`~femreg.io.Frames` ((n, h, w) float32, see module doc).

    Parameters
    ----------
    spacing : (dx, dy) mm, optional
        Overrides; ``dx`` may be None to take ``c/(2 sf)`` from the header; ``dy`` is required.
    sound_speed : float, m/s, optional
        Speed of sound for the axial spacing (default 1540).
    """
    path = Path(path)
    hdr = read_header(path)
    n, w, h = hdr["frames"], hdr["w"], hdr["h"]
    frame_bytes = w * h * 2
    size = os.path.getsize(path)
    body = size - HEADER_SIZE
    if body == n * frame_bytes and not _tag_sequence(path, n, frame_bytes):
        tagged = False
    elif body == n * (frame_bytes + 4):
        tagged = True
    elif body == n * frame_bytes:   # the frame numbers of a tagged file, with its end cut off
        raise fail(path, f"truncated: frame tags present, so {n} frame(s) of {h} x {w} int16 need "
                         f"{n * (frame_bytes + 4)} data bytes after the header, found {body}")
    else:
        full = body // frame_bytes
        kind = "truncated" if body < n * frame_bytes else "size mismatch"
        raise fail(path, f"{kind}: {body} data bytes after the header, but {n} frame(s) of {h} x {w} int16 need "
                         f"{n * frame_bytes} (or {n * (frame_bytes + 4)} with frame tags); "
                         f"room for {full} whole frame(s)")
    stride = frame_bytes + (4 if tagged else 0)
    idx = select_frames(path, np.arange(n), frames)
    out = np.empty((idx.size, h, w), dtype=np.float32)
    tags = []
    try:
        with open(path, "rb") as fh:
            for k, i in enumerate(idx):
                fh.seek(HEADER_SIZE + int(i) * stride)
                if tagged:
                    tags.append(struct.unpack("<i", fh.read(4))[0])
                blob = fh.read(frame_bytes)
                # column-major: w lines of h samples
                out[k] = np.frombuffer(blob, dtype="<i2").reshape(w, h).T
    except (OSError, struct.error, ValueError) as exc:
        raise fail(path, f"cannot read frame data ({exc})") from None

    c = SOUND_SPEED if sound_speed is None else float(sound_speed)
    if not (np.isfinite(c) and c > 0):
        raise InputError(f"sound_speed must be positive (m/s), got {sound_speed!r}")
    user = check_spacing(spacing, allow_none=True)
    dx = None
    if hdr["sf"] > 0:
        dx = c * 1e3 / (2.0 * hdr["sf"])  # m/s -> mm/s, over the two-way sampling rate
    elif user is None or user[0] is None:
        raise fail(path, f"bad header field sf (sampling frequency) = {hdr['sf']}; give spacing=(dx, dy)")
    need = "Ultrasonix .rf files do not store the lateral line pitch"
    sug = None
    if dx is not None:      # the half of the spacing the header gives (its field sf, in Hz)
        need += " (fs_Hz below: the header's sf)"
        sug = spacing_suggestion({"fs_Hz": hdr["sf"], **({} if sound_speed is None else {"c": c})})
    sp = merge_spacing(path, (dx, None), spacing, required_msg=need, suggestion=sug)
    meta = {"format": "ultrasonix", "header": hdr, "frame_tags": tagged, "sound_speed": c, "stored_dtype": "int16"}
    if tagged:
        meta["frame_numbers"] = tags
    return validate_frames(path, out, sp, (0.0, 0.0), meta, None)


def _tag_sequence(path, n: int, frame_bytes: int) -> bool:
    """True when the int32 words where a tagged file keeps its frame numbers count up by one: the data of a
    tagged file cut short by exactly ``4 n`` bytes, which by size alone would pass for an untagged file.  Real RF
    samples essentially never form such a sequence (needs n >= 2)."""
    if n < 2:
        return False
    stride = frame_bytes + 4
    with open(path, "rb") as fh:
        tags = []
        for k in range(n):
            fh.seek(HEADER_SIZE + k * stride)
            word = fh.read(4)
            if len(word) < 4:
                break
            tags.append(struct.unpack("<i", word)[0])
    return len(tags) >= 2 and all(b == a + 1 for a, b in zip(tags, tags[1:]))


def write_ultrasonix(path, frames, spacing=None, *, sampling_frequency=None, sound_speed=SOUND_SPEED,
                     frame_tags=False, header=None):
    """Write int16 RF ``frames`` ((axial, lateral) or (n, axial, lateral)) as an Ultrasonix ``.rf`` file.

    ``sampling_frequency`` (Hz) defaults to ``c / (2 dx)`` from ``spacing`` so that reading back gives the same
    axial spacing.  Values are rounded to int16 (an error if out of range).  ``header`` overrides header fields
    (``txf``, the transmit frequency in Hz, is written as 0, unknown, unless given there).
    """
    path = Path(path)
    arr = np.asarray(frames)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise InputError(f"frames must be 2D or 3D, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError("frames contain NaN/Inf")
    r = np.rint(arr)
    if r.size and (r.min() < -32768 or r.max() > 32767):
        raise InputError(f"RF values [{r.min()}, {r.max()}] do not fit int16 (scale them first)")
    n, h, w = arr.shape
    if sampling_frequency is None:
        if spacing is None:
            raise InputError("give spacing or sampling_frequency for the .rf header")
        sampling_frequency = sound_speed * 1e3 / (2.0 * float(spacing[0]))
    hdr = dict.fromkeys(HEADER_FIELDS, 0)
    hdr.update(type=RF_TYPE, frames=n, w=w, h=h, ss=16, ur_x=w - 1, br_x=w - 1, br_y=h - 1, bl_y=h - 1,
               sf=int(round(sampling_frequency)), txf=0, dr=20, ld=w)
    # txf 0: the transmit frequency is not known here (header={"txf": Hz} gives it); a made-up one would mislead
    hdr.update(header or {})
    with open(path, "wb") as fh:
        fh.write(_STRUCT.pack(*(int(hdr[k]) for k in HEADER_FIELDS)))
        for k in range(n):
            if frame_tags:
                fh.write(struct.pack("<i", k + 1))
            fh.write(np.ascontiguousarray(r[k].T, dtype="<i2").tobytes())  # column-major
    return [path]
