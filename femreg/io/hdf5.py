"""Plain HDF5 files (``.h5``, ``.hdf5``, ``.hdf``; any HDF5 file without MATLAB's header) of RF or IQ frames.

Research scanners and their Python or MATLAB exports write beamformed frames as an HDF5 dataset with no agreed
layout or naming.  What femreg reads:

* the dataset: ``variable=`` (a path, e.g. ``"acq/rf"``), else one whose name is ``rf`` or ``frames`` anywhere in
  the file, else the only numeric dataset of 2 or 3 dimensions (each at least 2 long);
* its layout: a 3D dataset holds the frames on its first axis (numpy's ``(frame, axial, lateral)``, and MATLAB's
  ``h5write`` of ``rf(axial, lateral, frame)``, which HDF5 shows reversed as ``(frame, lateral, axial)``), unless
  that leaves frames thinner than :data:`femreg.io.matlab.MIN_FRAME_SAMPLES` while the last axis would not (then
  the frames are last).  Whether a frame is ``(axial, lateral)`` or ``(lateral, axial)`` the RF carrier tells
  (:func:`femreg.orientation.axial_carrier_ratio`: along the depth only); frames carrying it along their second
  axis are transposed and ``metadata["layout"]`` says so.  IQ (complex) and envelope frames are read as stored;
* spacing (mm) and origin: a dataset or an attribute (of the frames' dataset or of the file) named ``spacing`` /
  ``origin``.  Without one the error names the spacing the file's attributes imply, if they hold a sampling
  frequency and a pitch (:func:`femreg.io.checks.spacing_suggestion`), but never applies it: units in attributes are
  a guess.

Scalar attributes of the file and of the dataset, and scalar datasets (by their path, e.g. ``probe/fs``), are kept
in ``metadata["fields"]``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FileFormatError, InputError, pass_as
from .checks import AXIS_MAX, axis_fields, check_origin, fail, merge_spacing, spacing_suggestion, validate_frames

__all__ = ["read_hdf5", "EXTENSIONS"]

EXTENSIONS = (".h5", ".hdf5", ".hdf", ".he5")
PREFERRED = ("rf", "frames")


def _scalars(attrs) -> dict:
    """The numeric and short text attributes of an HDF5 object, as plain Python values."""
    out = {}
    for k, v in attrs.items():
        v = v.decode("utf-8", "replace") if isinstance(v, bytes) else v
        a = np.asarray(v)
        if a.dtype.kind in "iuf" and a.size == 1:
            out[str(k)] = a.item()
        elif a.dtype.kind in "iuf" and 1 < a.size <= 4:
            out[str(k)] = a.ravel().tolist()
        elif isinstance(v, str) and len(v) <= 200:
            out[str(k)] = v
    return out


def _datasets(f) -> dict:
    """{path: dataset} of every dataset in the file."""
    import h5py

    found = {}

    def keep(name, obj):          # returns None: visititems stops at the first value returned
        if isinstance(obj, h5py.Dataset):
            found[name] = obj

    f.visititems(keep)
    return found


def _choose(path, dsets: dict, variable) -> str:
    if variable is not None:
        key = str(variable).strip("/")
        if key not in dsets:
            raise fail(path, f"missing dataset {variable!r}; available: {', '.join(sorted(dsets)) or 'none'}")
        return key
    for key in sorted(dsets):
        if key.rsplit("/", 1)[-1].lower() in PREFERRED:
            return key
    good = [k for k, d in dsets.items() if d.dtype.kind in "iufc" and d.ndim in (2, 3) and min(d.shape) > 1]
    if len(good) == 1:
        return good[0]
    if not good:
        raise fail(path, f"no 2D/3D numeric dataset found (datasets: {', '.join(sorted(dsets)) or 'none'})")
    raise fail(path, f"several 2D/3D datasets ({', '.join(sorted(good))}); choose one with "
                     + pass_as("variable= (CLI: --variable NAME)", "--variable NAME"))


def _named(f, ds, name):
    """A dataset beside the frames or at the root, or an attribute of the frames or the file, called ``name``."""
    parent = ds.parent
    for where in (parent, f):
        if name in where and getattr(where[name], "shape", None) is not None:
            return where[name][()]
    for attrs in (ds.attrs, f.attrs):
        if name in attrs:
            return attrs[name]
    return None


def _layout(arr, meta):
    """(frame, axial, lateral) from the stored array (module docstring), ``meta["layout"]`` saying what was done."""
    from .matlab import MIN_FRAME_SAMPLES

    if arr.ndim == 3 and min(arr.shape[1:]) < MIN_FRAME_SAMPLES <= min(arr.shape[:2]):
        arr = np.moveaxis(arr, -1, 0)
        meta["layout"] = f"frames on the last axis ({arr.shape[0]} frames)"
    if np.iscomplexobj(arr):
        return arr
    from ..orientation import CARRIER_RATIO, axial_carrier_ratio

    first = arr if arr.ndim == 2 else arr[0]
    as_stored, exchanged = axial_carrier_ratio(first), axial_carrier_ratio(first.T)
    if exchanged < CARRIER_RATIO and not as_stored < CARRIER_RATIO:
        arr = np.swapaxes(arr, -1, -2)
        meta["layout"] = ((meta["layout"] + "; " if "layout" in meta else "")
                          + f"frames stored (lateral, axial): transposed, the RF carrier runs along the stored "
                            f"last axis ({arr.shape[-2]} samples)")
    return arr


def read_hdf5(path, *, variable=None, spacing=None, frames=None, **_ignored) -> dict:
    """Read RF (or IQ) frames from a plain HDF5 file: the fields of a :class:`~femreg.io.Frames` (module
    docstring)."""
    import h5py

    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            dsets = _datasets(f)
            name = _choose(path, dsets, variable)
            ds = dsets[name]
            if ds.dtype.kind not in "iufc":
                raise fail(path, f"dataset {name!r} is not numeric ({ds.dtype})")
            if ds.size * ds.dtype.itemsize > 1 << 34:
                raise fail(path, f"dataset {name!r} claims {ds.shape} {ds.dtype} (over 16 GiB)")
            arr = ds[()]
            stored = str(ds.dtype) if ds.dtype.kind != "c" else f"complex {np.dtype(ds.dtype).name}"
            file_spacing, origin = _named(f, ds, "spacing"), _named(f, ds, "origin")
            # scalar datasets are header fields too (an export's probe/fs, as MATLAB's scalar variables)
            scalars = {k: d[()] for k, d in dsets.items() if k != name and d.size == 1
                       and d.dtype.kind in "iuf"}
            attrs = {**_scalars(scalars), **_scalars(f.attrs), **_scalars(ds.attrs)}
            axes = axis_fields((k, d[()]) for k, d in dsets.items() if k != name and 3 <= d.size <= AXIS_MAX
                               and d.dtype.kind in "iuf")
    except (FileFormatError, InputError):
        raise
    except Exception as exc:  # h5py raises OSError, KeyError, RuntimeError on corrupt files
        raise fail(path, f"corrupt or truncated HDF5 file ({type(exc).__name__}: {exc})") from None
    meta = {"format": "hdf5", "variable": name, "variables": sorted(dsets), "stored_dtype": stored}
    if attrs:
        meta["fields"] = attrs
    if axes:
        meta["axes"] = axes
    arr = _layout(np.asarray(arr), meta)
    if file_spacing is not None:
        try:
            file_spacing = tuple(np.asarray(file_spacing, float).ravel())
        except (TypeError, ValueError):
            raise fail(path, "'spacing' is not numeric") from None
        if len(file_spacing) != 2:
            raise fail(path, f"'spacing' has {len(file_spacing)} values, expected 2 (dx, dy) mm")
    sp = merge_spacing(path, file_spacing, spacing, n=2, required_msg="no 'spacing' in the HDF5 file",
                       suggestion=spacing_suggestion(attrs))
    origin = check_origin(origin, path, n=2) if origin is not None else (0.0, 0.0)
    return validate_frames(path, arr, sp, origin, meta, frames)
