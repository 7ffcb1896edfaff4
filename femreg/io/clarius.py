"""Clarius research exports (hand-held Clarius scanners: ``*_rf.raw`` RF, ``*_env.raw`` envelope).

Layout
------
A header of 5 little-endian int32::

    id, frames, lines, samples, samplesize

then, for every frame, an int64 time stamp followed by ``lines x samples`` samples of ``samplesize`` bytes, line
after line (each line's samples contiguous).  ``samplesize`` 2 is int16 RF, 1 uint8 envelope.  The file is
recognised by its size, which must be exactly ``20 + frames * (8 + lines * samples * samplesize)``: a
headerless ``.raw`` file matches that by chance essentially never.

Settings: the export writes a YAML file beside the data (``scan_rf.yml`` for ``scan_rf.raw``) with the sampling
rate (e.g. ``sampling rate: 40 MHz``) and the probe.  Its numbers are listed and the ``--spacing`` they imply is
named (``c / (2 fs)`` axially, the probe's pitch laterally where stated), as a headerless file's JSON sidecar;
never applied: the spacing is the user's to pass.  The sampling rate and transmit frequency are what a given
spacing is held against (:func:`femreg.orientation.check_sampling`).  ``delay samples`` is listed, not taken for
the first sample's depth: Clarius's example readers and PyQuantUS's parser leave it out (the latter spaces the
samples from 0 to the imaging depth), and on Clarius's example exports ``samples x c / (2 fs)`` equals the
``imaging depth`` (3120 samples at 60 MHz: 40.0 mm of 40), which a record starting 62 samples deep would overshoot.
"""
from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from ..errors import InputError, pass_as
from .checks import fail, merge_spacing, parse_dtype, spacing_suggestion
from .frames import finalize

HEADER_FIELDS = ("id", "frames", "lines", "samples", "samplesize")
HEADER_SIZE = 20
STAMP_SIZE = 8
#: sample size in bytes -> stored type
SAMPLE_TYPES = {2: "<i2", 1: "u1"}
#: header ids of IQ exports (0: B-mode IQ, 3: pulsed-wave Doppler IQ): two samples per depth, I and Q
IQ_IDS = (0, 3)


def _header(path) -> tuple | None:
    """``(file size in bytes, header fields)`` of the first :data:`HEADER_SIZE` bytes of ``path`` read as a Clarius
    header, or None where the file cannot be read or is shorter."""
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as fh:
            raw = fh.read(HEADER_SIZE)
    except OSError:
        return None
    if len(raw) < HEADER_SIZE:
        return None
    return size, dict(zip(HEADER_FIELDS, (int(v) for v in np.frombuffer(raw, "<i4"))))


def sniff(path, head=None) -> dict | None:
    """The header fields when ``path`` is a Clarius raw file (its size matches the header exactly), else None.
    ``head``: :func:`_header`'s reading of ``path``, if already made (read here otherwise)."""
    head = _header(path) if head is None else head
    if head is None:
        return None
    size, hdr = head
    if not (0 < hdr["frames"] <= 1 << 20 and 0 < hdr["lines"] <= 1 << 16 and 0 < hdr["samples"] <= 1 << 20
            and hdr["samplesize"] in (1, 2, 4, 8)):
        return None
    frame = hdr["lines"] * hdr["samples"] * hdr["samplesize"]
    if size == HEADER_SIZE + hdr["frames"] * (STAMP_SIZE + frame):
        return hdr
    if hdr["id"] in IQ_IDS and size == HEADER_SIZE + hdr["frames"] * (STAMP_SIZE + 2 * frame):
        # IQ exports hold an I and a Q sample per depth: recognised, to be refused by name
        return dict(hdr, iq=True)
    return None


def cut_short(path, head=None) -> str:
    """A message when ``path`` starts with a plausible Clarius header (RF or envelope samples, sizes in range) but
    is shorter than its frames need (a copy or transfer cut short), naming the whole frames it holds; else "".
    ``head`` as :func:`sniff`'s."""
    head = _header(path) if head is None else head
    if head is None:
        return ""
    size, hdr = head
    if not (0 < hdr["frames"] <= 1 << 16 and 0 < hdr["lines"] <= 4096 and 16 <= hdr["samples"] <= 1 << 16
            and hdr["samplesize"] in SAMPLE_TYPES):
        return ""
    stride = STAMP_SIZE + hdr["lines"] * hdr["samples"] * hdr["samplesize"]
    need = HEADER_SIZE + hdr["frames"] * stride
    if not size < need:
        return ""
    return (f"truncated Clarius raw export: its header states {hdr['frames']} frame(s) of {hdr['samples']} samples "
            f"x {hdr['lines']} lines ({need} bytes), the file has {size}; room for "
            f"{(size - HEADER_SIZE) // stride} whole frame(s)")


_NUMBER = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z/]*)\s*$")


def settings_fields(path) -> tuple:
    """``(name, fields)`` of the YAML settings beside a Clarius raw file (``scan_rf.yml`` / ``.yaml``): its
    numbers, nested keys joined by ``/`` (``probe/pitch``), a value's unit appended to its name (``sampling
    rate: 40 MHz`` -> ``sampling rate_MHz`` = 40, which :func:`~femreg.io.checks.spacing_suggestion` reads);
    ``(None, {})`` without one.  Indented ``key: value`` lines are read without a YAML library."""
    path = Path(path)
    for side in (path.with_suffix(".yml"), path.with_suffix(".yaml")):
        if not side.is_file():
            continue
        try:
            text = side.read_text(errors="replace")
        except OSError as exc:
            return f"{side.name} not read ({exc.strerror or exc})", {}
        out, stack = {}, []           # stack: (indent, key) of the open mappings
        for line in text.splitlines():
            body = line.split("#", 1)[0].rstrip()
            if not body.strip() or body.strip() in ("---", "...") or body.lstrip().startswith("- ") \
                    or ":" not in body:
                continue
            indent = len(body) - len(body.lstrip())
            key, _, value = body.strip().partition(":")
            while stack and stack[-1][0] >= indent:
                stack.pop()
            if not value.strip():
                stack.append((indent, key.strip()))
                continue
            m = _NUMBER.match(value)
            if m is None:
                continue
            v = float(m.group(1))
            if not math.isfinite(v):
                continue
            name = "/".join([k for _, k in stack] + [key.strip()])
            out[name + (f"_{m.group(2)}" if m.group(2) else "")] = v
        return side.name, out
    return None, {}


def read_clarius(path, *, spacing=None, frames=None, shape=None, dtype=None, header=None, **_ignored):
    """Read a Clarius raw file: the fields of a :class:`~femreg.io.Frames` (see the module doc), frames
    ``(n, samples, lines)`` float32, the time stamps (ns) and the settings file's numbers in the metadata.
    ``header``: :func:`sniff`'s fields of ``path`` where the caller has them (the file's header is not read again)."""
    from .checks import select_frames

    path = Path(path)
    hdr = sniff(path) if header is None else header
    if hdr is None:
        raise fail(path, "not a Clarius raw file (its size does not match a 5-field header's frames)")
    n, nl, ns, sz = hdr["frames"], hdr["lines"], hdr["samples"], hdr["samplesize"]
    if hdr.get("iq"):
        raise fail(path, f"a Clarius IQ export (header id {hdr['id']}: I and Q of {ns} depths x {nl} lines per "
                         "frame): its demodulation frequency is not stored with it, so it cannot be remodulated to "
                         "RF here; export the RF data (`*_rf.raw`, header id 2) from the Clarius app instead")
    if sz not in SAMPLE_TYPES:
        raise fail(path, f"Clarius raw file of {sz}-byte samples: only RF (2-byte int16) and envelope (1-byte) "
                         "data are read")
    stored = np.dtype(SAMPLE_TYPES[sz])
    given = None if shape is None else tuple(int(s) for s in np.asarray(shape).ravel())
    if given is not None and given[-2:] != (ns, nl) and given[-2:] != (nl, ns):
        raise InputError(f"{path}: its Clarius header states {n} frame(s) of {ns} samples x {nl} lines; "
                         + pass_as("shape", "--shape") + f" {' '.join(map(str, given))} disagrees: leave it out")
    if dtype is not None and parse_dtype(dtype, None).itemsize != sz:
        raise InputError(f"{path}: its Clarius header states {stored.name} samples ({sz} byte(s)); "
                         + pass_as("dtype", "--dtype") + f" {dtype} disagrees: leave it out")
    rec = np.dtype([("stamp", "<i8"), ("data", stored, (nl, ns))])
    try:
        blob = np.fromfile(path, dtype=rec, count=n, offset=HEADER_SIZE)
    except (OSError, ValueError) as exc:
        raise fail(path, f"cannot read frame data ({exc})") from None
    idx = select_frames(path, np.arange(n), frames)
    # line after line: (lines, samples) per frame -> (samples, lines), axial first
    arr = np.ascontiguousarray(blob["data"][idx].transpose(0, 2, 1)).astype(np.float32)
    stamps = blob["stamp"][idx]
    side, fields = settings_fields(path)
    sug = spacing_suggestion(fields) if fields else None
    sp = merge_spacing(path, None, spacing, required_msg="Clarius raw files store no spacing"
                       + (f" ({side} beside it holds the settings)" if side else ""),
                       frame_shape=arr.shape[-2:], suggestion=sug)
    meta = {"format": "clarius", "header": hdr, "stored_dtype": stored.name, "layout": "stored line by line",
            "timestamps_ns": [int(s) for s in stamps]}
    if len(stamps) > 1:
        dt = np.diff(stamps.astype(np.float64)) * 1e-9
        if np.all(dt > 0):
            meta["frame_rate_hz"] = round(1.0 / float(np.median(dt)), 3)
    if side:
        meta["sidecar"] = side
        if fields:
            meta["fields"] = fields
    return finalize(path, arr, sp, (0.0, 0.0), meta, None)
