"""``save_frames``: write frames in every format :func:`~femreg.io.read_frames` reads (round trips, test data,
conversion for other tools)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .checks import FORMATS, check_origin, check_spacing, parse_dtype

__all__ = ["save_frames", "save_volumes"]


def save_frames(path, frames, spacing=None, *, origin=(0.0, 0.0), format=None, dtype=None, byte_order="little",
                variable="rf", mat_version="5", frame_tags=False, sampling_frequency=None, sound_speed=1540.0):
    """Write ``frames`` ((axial, lateral) or (n, axial, lateral)) to ``path``.

    Parameters
    ----------
    path : str or Path
        Format from the extension (or ``format=``): ``.npy`` (array only), ``.npz`` (``rf``/``variable``,
        ``spacing``, ``origin``), ``.mat`` (``mat_version`` '5', '7' or '7.3'; MATLAB order
        ``rf(axial, lateral, frame)``), ``.mhd`` (+ ``.raw``) / ``.mha``, ``.raw`` (headerless, C order),
        ``.rf`` (Ultrasonix int16, with ``frame_tags`` optionally).
    spacing : (dx, dy) mm
        Stored where the format has room for it (npz, mat, MetaImage; the axial one in .rf as ``sf``).
    dtype : on-disk sample type for raw / MetaImage (default: float32 unless the array is float64/integer).
    byte_order : {'little', 'big'}
        For raw and MetaImage.

    Returns
    -------
    list of Path
        The files written.
    """
    path = Path(path)
    arr = np.asarray(frames)
    if arr.ndim not in (2, 3):
        raise InputError(f"frames must be (axial, lateral) or (n, axial, lateral), got shape {arr.shape}")
    if arr.dtype.kind not in "biuf":
        raise InputError(f"frames must be real numbers, got dtype {arr.dtype}")
    sp = check_spacing(spacing) if spacing is not None else None
    origin = check_origin(origin)
    fmt = format or FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise InputError(f"{path}: unknown extension {path.suffix!r}; use one of {', '.join(sorted(FORMATS))}")
    if fmt in ("npy", "npz"):
        return _write_numpy(path, fmt, arr, sp, origin, variable)
    if fmt == "mat":
        from .matlab import write_mat

        return write_mat(path, arr, sp, origin, variable=variable, version=mat_version)
    if fmt == "metaimage":
        from .metaimage import write_metaimage

        if sp is None:
            raise InputError("MetaImage needs spacing=(dx, dy)")
        return write_metaimage(path, arr, sp, origin, dtype=dtype, byte_order=byte_order)
    if fmt == "raw":
        dt = parse_dtype(dtype if dtype is not None else (arr.dtype if arr.dtype.kind in "iuf" else "float32"),
                         byte_order)
        np.ascontiguousarray(arr, dtype=dt).tofile(path)
        return [path]
    if fmt == "ultrasonix":
        from .ultrasonix import write_ultrasonix

        return write_ultrasonix(path, arr, sp, sampling_frequency=sampling_frequency, sound_speed=sound_speed,
                                frame_tags=frame_tags)
    if fmt == "dicom":
        raise InputError(f"{path}: femreg reads DICOM but does not write it; save the frames as .npz (spacing kept)")
    raise InputError(f"unknown format {fmt!r}")


def _write_numpy(path, fmt, arr, spacing, origin, variable) -> list:
    """``.npy`` (the array only) or ``.npz`` (``variable``, ``origin`` and, when known, ``spacing``) of frames
    or volumes; returns ``[path]``."""
    if fmt == "npy":
        np.save(path, arr, allow_pickle=False)
        return [path]
    data = {variable: arr, "origin": np.asarray(origin)}
    if spacing is not None:
        data["spacing"] = np.asarray(spacing)
    np.savez(path, **data)
    return [path]


def save_volumes(path, volumes, spacing=None, *, origin=(0.0, 0.0, 0.0), format=None, dtype=None,
                 byte_order="little", variable="rf", mat_version="5"):
    """Write a volume (axial, lateral, elevational) or a volume sequence (n, axial, lateral, elevational) in a
    layout :func:`~femreg.io.read_volumes` reads back: ``.npy`` (array only), ``.npz`` (``variable``,
    ``spacing`` and ``origin`` of three values), ``.mat`` (``rf(axial, lateral, elevational[, frame])``),
    ``.mhd`` + ``.raw`` / ``.mha`` (NDims 3 / 4).  Returns the files written."""
    path = Path(path)
    arr = np.asarray(volumes)
    if arr.ndim not in (3, 4):
        raise InputError(f"volumes must be (axial, lateral, elevational) or (n, axial, lateral, elevational), "
                         f"got shape {arr.shape}")
    if arr.dtype.kind not in "biuf":
        raise InputError(f"volumes must be real numbers, got dtype {arr.dtype}")
    sp = check_spacing(spacing, n=3) if spacing is not None else None
    origin = check_origin(origin, n=3)
    fmt = format or FORMATS.get(path.suffix.lower())
    if fmt in ("npy", "npz"):
        return _write_numpy(path, fmt, arr, sp, origin, variable)
    if fmt == "mat":
        from .matlab import write_mat_volume

        return write_mat_volume(path, arr, sp, origin, variable=variable, version=mat_version)
    if fmt == "metaimage":
        from .metaimage import write_metaimage_volume

        if sp is None:
            raise InputError("MetaImage needs spacing=(dx, dy, dz)")
        return write_metaimage_volume(path, arr, sp, origin, dtype=dtype, byte_order=byte_order)
    raise InputError(f"{path}: volumes are written as .npy, .npz, .mat or .mhd/.mha, not {path.suffix!r}")
