"""The :class:`Frames` container returned by every reader, and the checks every reader shares.

Layout convention (the whole project's): a frame is a 2D array (axial, lateral) = (x, y), axis 0 runs
along a scan line (samples, depth), axis 1 across scan lines; lengths in mm; pixel ``[i, j]`` has its centre
at ``origin + (i*dx, j*dy)``.  A sequence is stacked on a leading frame axis: ``(n, axial, lateral)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FileFormatError, InputError

__all__ = ["Frames"]


@dataclass
class Frames:
    """RF (or B-mode) frames read from a file.

    Attributes
    ----------
    frames : (n, axial, lateral) float32 or float64
        Samples; float64 only when the file stores float64, float32 otherwise (integers are converted).
        Always finite.
    spacing : (dx, dy) float, mm
        Axial sample spacing and lateral line spacing.
    origin : (x0, y0) float, mm
        Centre of pixel ``[0, 0]``.
    metadata : dict
        Format name and header fields (``metadata["format"]``; e.g. the Ultrasonix header, MetaImage keys).
    source : pathlib.Path or None
        The file (or directory) read.
    """

    frames: np.ndarray
    spacing: tuple[float, float]
    origin: tuple[float, float] = (0.0, 0.0)
    metadata: dict[str, Any] = field(default_factory=dict)
    source: Path | None = None

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        """Shape of one frame, (axial, lateral)."""
        return (int(self.frames.shape[1]), int(self.frames.shape[2]))

    @property
    def format(self) -> str:
        return str(self.metadata.get("format", ""))

    def __len__(self) -> int:
        return self.n_frames

    def __getitem__(self, k) -> np.ndarray:
        """Frame ``k`` as a 2D (axial, lateral) array (or a sub-stack for a slice)."""
        return self.frames[k]

    def __iter__(self):
        return iter(self.frames)

    def save(self, path, **kwargs):
        """Write these frames with :func:`femreg.io.save_frames` (format from the extension)."""
        from .writers import save_frames

        return save_frames(path, self.frames, self.spacing, origin=self.origin, **kwargs)


# ----------------------------------------------------------------------------------------------- checks

def fail(path, problem: str) -> FileFormatError:
    """A :class:`FileFormatError` whose one-line message names the file and the problem."""
    problem = " ".join(str(problem).split())  # one line, whatever the wrapped library said
    return FileFormatError(f"{path}: {problem}")


def check_spacing(value, what: str = "spacing", allow_none: bool = False):
    """Validate a ``(dx, dy)`` pair in mm: two positive finite numbers (or None entries if allowed)."""
    if value is None:
        return None
    try:
        vals = list(np.asarray(value, dtype=object).ravel())
    except Exception as exc:  # pragma: no cover - np.asarray on odd objects
        raise InputError(f"{what} must be two numbers (dx, dy) in mm, got {value!r}") from exc
    if len(vals) != 2:
        raise InputError(f"{what} must be two numbers (dx, dy) in mm, got {value!r}")
    out = []
    for v in vals:
        if v is None and allow_none:
            out.append(None)
            continue
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise InputError(f"{what} must be two numbers (dx, dy) in mm, got {value!r}") from None
        if not (math.isfinite(f) and f > 0):
            raise InputError(f"{what} must be positive and finite (mm), got {value!r}")
        out.append(f)
    return tuple(out)


def check_origin(value, path=None):
    if value is None:
        return (0.0, 0.0)
    try:
        arr = np.asarray(value, dtype=float).ravel()
    except (TypeError, ValueError):
        raise (fail(path, f"origin must be two numbers, got {value!r}") if path
               else InputError(f"origin must be two numbers, got {value!r}")) from None
    if arr.size != 2 or not np.all(np.isfinite(arr)):
        msg = f"origin must be two finite numbers (x0, y0) in mm, got {value!r}"
        raise fail(path, msg) if path else InputError(msg)
    return (float(arr[0]), float(arr[1]))


def merge_spacing(path, file_spacing, user_spacing, *, required_msg: str | None = None):
    """Spacing from the file, overridden component-wise by the user's (None entries keep the file's)."""
    user = check_spacing(user_spacing, allow_none=True)
    file_sp = list(file_spacing) if file_spacing is not None else [None, None]
    if user is not None:
        file_sp = [u if u is not None else f for u, f in zip(user, file_sp)]
    if any(v is None for v in file_sp):
        missing = " and ".join(n for n, v in zip(("axial dx", "lateral dy"), file_sp) if v is None)
        msg = required_msg or "this format stores no pixel spacing"
        raise InputError(f"{path}: {missing} spacing unknown ({msg}); give spacing=(dx, dy) in mm "
                         "(CLI: --spacing DX DY)")
    try:
        return check_spacing(file_sp, what="spacing")
    except InputError as exc:
        raise fail(path, f"bad spacing {tuple(file_sp)} (must be positive, finite, mm)") from exc


def select_frames(path, arr: np.ndarray, frames):
    """Apply a frame selection (int, slice, sequence of ints, or None = all) to an (n, ...) stack."""
    if frames is None:
        return arr
    n = arr.shape[0]
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
        raise InputError(f"{path}: frame selection {frames!r} selects no frame (the file has {n})")
    bad = idx[(idx < -n) | (idx >= n)]
    if bad.size:
        raise InputError(f"{path}: frame index {int(bad[0])} out of range (the file has {n} frame(s))")
    return arr[idx]


def finalize(path, arr, spacing, origin=(0.0, 0.0), metadata=None, frames=None) -> Frames:
    """Shared tail of every reader: shape (n, axial, lateral), float dtype, finite values, selection."""
    arr = np.asarray(arr)
    if arr.dtype.kind == "c":
        raise fail(path, f"complex data ({arr.dtype}) is not RF; store the real RF samples")
    if arr.dtype.kind not in "biuf":
        raise fail(path, f"data of type {arr.dtype} is not numeric")
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise fail(path, f"data has {arr.ndim} dimension(s) {arr.shape}; expected 2 (axial, lateral) "
                         "or 3 (frames, axial, lateral)")
    if min(arr.shape) < 1:
        raise fail(path, f"data is empty, shape {arr.shape}")
    if arr.shape[1] < 2 or arr.shape[2] < 2:
        raise fail(path, f"frame shape {arr.shape[1:]} is degenerate (need at least 2 x 2 samples)")
    arr = select_frames(path, arr, frames)
    metadata = {**(metadata or {}), "stored_dtype": (metadata or {}).get("stored_dtype", arr.dtype.name)}
    out_dtype = np.float64 if (arr.dtype.kind == "f" and arr.dtype.itemsize == 8) else np.float32
    # native byte order, C-contiguous, own memory
    arr = np.ascontiguousarray(arr, dtype=np.dtype(out_dtype).newbyteorder("="))
    finite = np.isfinite(arr)
    if not finite.all():
        n_bad = int(arr.size - np.count_nonzero(finite))
        raise fail(path, f"data contains {n_bad} NaN/Inf value(s)")
    meta = dict(metadata or {})
    return Frames(frames=arr, spacing=tuple(float(s) for s in spacing), origin=check_origin(origin, path),
                  metadata=meta, source=Path(path))
