"""The :class:`Frames` container returned by every reader (the checks they share: :mod:`femreg.io.checks`).

Layout convention (the whole project's): a frame is a 2D array (axial, lateral) = (x, y), axis 0 runs
along a scan line (samples, depth), axis 1 across scan lines; lengths in mm; pixel ``[i, j]`` has its centre
at ``origin + (i*dx, j*dy)``.  A sequence is stacked on a leading frame axis: ``(n, axial, lateral)``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .checks import check_origin, check_spacing, fail, merge_spacing, select_frames, validate_frames  # noqa: F401
from .writers import save_frames

__all__ = ["Frames", "Volumes"]


class _Stack:
    """What :class:`Frames` and :class:`Volumes` share: a stack ``frames`` with its frame axis first, read
    from a file whose format name is ``metadata["format"]``; ``stack[k]`` is frame (or volume) ``k``, or a
    sub-stack for a slice."""

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def format(self) -> str:
        return str(self.metadata.get("format", ""))

    def __len__(self) -> int:
        return self.n_frames

    def __getitem__(self, k) -> np.ndarray:
        return self.frames[k]

    def __iter__(self):
        return iter(self.frames)


@dataclass
class Frames(_Stack):
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
    def shape(self) -> tuple[int, int]:
        """Shape of one frame, (axial, lateral)."""
        return (int(self.frames.shape[1]), int(self.frames.shape[2]))

    def save(self, path, **kwargs):
        """Write these frames with :func:`femreg.io.save_frames` (format from the extension)."""
        return save_frames(path, self.frames, self.spacing, origin=self.origin, **kwargs)


def finalize(path, arr, spacing, origin=(0.0, 0.0), metadata=None, frames=None) -> Frames:
    """Shared tail of every reader (:func:`femreg.io.checks.validate_frames`) as a :class:`Frames`."""
    return Frames(**validate_frames(path, arr, spacing, origin, metadata, frames))


@dataclass
class Volumes(_Stack):
    """RF volumes read from a file (:func:`femreg.io.read_volumes`).

    Attributes
    ----------
    frames : (n, axial, lateral, elevational) float32 or float64
        One volume per frame (a single volume: n = 1); finite.
    spacing : (dx, dy, dz) float, mm
        Axial sample, lateral line and elevational plane spacing.
    origin : (x0, y0, z0) float, mm
        Centre of voxel ``[0, 0, 0]``.
    metadata : dict
        Format name and header fields.
    source : pathlib.Path or None
    """

    frames: np.ndarray
    spacing: tuple[float, float, float]
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    metadata: dict[str, Any] = field(default_factory=dict)
    source: Path | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        """Shape of one volume, (axial, lateral, elevational)."""
        return tuple(int(v) for v in self.frames.shape[1:])

    def save(self, path, **kwargs):
        """Write these volumes with :func:`femreg.io.save_volumes` (format from the extension)."""
        from .writers import save_volumes

        return save_volumes(path, self.frames, self.spacing, origin=self.origin, **kwargs)


def finalize_volumes(path, arr, spacing, origin=(0.0, 0.0, 0.0), metadata=None, frames=None) -> Volumes:
    """Shared tail of every volume reader (:func:`femreg.io.checks.validate_volumes`) as a :class:`Volumes`."""
    from .checks import validate_volumes

    return Volumes(**validate_volumes(path, arr, spacing, origin, metadata, frames))
