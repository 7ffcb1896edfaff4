"""Plain HDF5 files (``.h5``, ``.hdf5``, ``.hdf``; any HDF5 file without MATLAB's header) of RF or IQ frames.

Research scanners and their Python or MATLAB exports write beamformed frames as an HDF5 dataset with no agreed
layout or naming.  What femreg reads:

* the dataset: ``variable=`` (a path, e.g. ``"acq/rf"``), else one whose name is ``rf`` or ``frames`` anywhere in
  the file, else the only numeric dataset of 2 or 3 dimensions (each at least 2 long);
* IQ frames stored as two real datasets, the in-phase and quadrature parts side by side in one group (``I`` /
  ``Q``, ``I_data`` / ``Q_data``, ``rf_i`` / ``rf_q``, ``real`` / ``imag``, ``iq_re`` / ``iq_im``: names that
  differ only in that part, of the same shape), or one compound dataset of such fields (MATLAB's ``real`` /
  ``imag``, ``r`` / ``i``, ``I`` / ``Q``), are read as one complex dataset ``I + 1j Q`` (:func:`_iq_pairs`): either
  half alone is not RF and no envelope either, and would register as such without a word;
* its layout: a 3D dataset holds the frames on its first axis (numpy's ``(frame, axial, lateral)``, and MATLAB's
  ``h5write`` of ``rf(axial, lateral, frame)``, which HDF5 shows reversed as ``(frame, lateral, axial)``), unless
  that leaves frames thinner than :data:`femreg.io.checks.MIN_FRAME_SAMPLES` while the last axis would not (then
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

import re
from pathlib import Path

import numpy as np

from ..errors import FileFormatError, InputError, pass_as
from .checks import AXIS_MAX, MIN_FRAME_SAMPLES, axis_fields, check_origin, fail, merge_spacing, spacing_suggestion, validate_frames

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


#: Name parts of the in-phase and quadrature halves of IQ data stored as two datasets (lower case).
IQ_PARTS = (("i", "q"), ("real", "imag"), ("re", "im"))
#: Field names of a compound dataset holding complex samples (lower case): in-phase, quadrature.
IQ_FIELDS = (("real", "imag"), ("r", "i"), ("re", "im"), ("i", "q"))


def iq_pair_names(arrays: dict) -> dict:
    """{in-phase name: quadrature name} of IQ data stored as two real arrays side by side, from ``{name: (shape,
    real)}`` (``real``: a real numeric array): names equal but for one of :data:`IQ_PARTS` (a whole word of the
    name, at its start or after ``_`` / ``-``, or followed by ``data`` / a separator), in one group (the same path
    up to the last ``/``), 2D or 3D, of the same shape.  HDF5 datasets and MATLAB variables (``IData`` /
    ``QData``) alike."""
    by_lower = {k.lower(): k for k in arrays}
    pairs = {}
    for key, (shape, real) in arrays.items():
        if not real or len(shape) not in (2, 3):
            continue
        group, _, base = key.rpartition("/")
        low = base.lower()
        for a, b in IQ_PARTS:
            for m in re.finditer(rf"(?:^|(?<=[_\-])){a}(?=$|[_\-]|data)", low):
                other = low[:m.start()] + b + low[m.end():]
                partner = by_lower.get(f"{group}/{other}".lower().lstrip("/"))
                if partner is not None and partner in arrays and tuple(arrays[partner][0]) == tuple(shape) \
                        and arrays[partner][1]:
                    pairs[key] = partner
    return pairs


def _iq_pairs(dsets: dict) -> dict:
    """{in-phase path: quadrature path} of IQ data stored as two real datasets in one group
    (:func:`iq_pair_names`)."""
    return iq_pair_names({k: (d.shape, d.dtype.kind in "iuf") for k, d in dsets.items()})


def _compound_iq(dtype):
    """(in-phase field, quadrature field) of a compound dtype that holds complex samples (:data:`IQ_FIELDS`), or
    None."""
    names = dtype.names or ()
    if len(names) != 2 or not all(dtype[k].kind in "iuf" for k in names):
        return None
    low = {k.lower(): k for k in names}
    for a, b in IQ_FIELDS:
        if a in low and b in low:
            return low[a], low[b]
    return None


def _choose(path, dsets: dict, variable, pairs=None) -> str:
    """The frames' dataset (module docstring); of an in-phase / quadrature pair (``pairs``) the in-phase path,
    whichever half ``variable`` names."""
    pairs = pairs or {}
    if variable is not None:
        key = str(variable).strip("/")
        if key not in dsets:
            raise fail(path, f"missing dataset {variable!r}; available: {', '.join(sorted(dsets)) or 'none'}")
        return next((i for i, q in pairs.items() if q == key), key)
    for key in sorted(dsets):
        if key.rsplit("/", 1)[-1].lower() in PREFERRED:
            return key
    quadrature = set(pairs.values())
    good = [k for k, d in dsets.items() if k not in quadrature and min(d.shape or (0,)) > 1 and d.ndim in (2, 3)
            and (d.dtype.kind in "iufc" or _compound_iq(d.dtype) is not None)]
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


def _as_complex(real, imag):
    """``real + 1j imag``, complex64 unless either part is double precision."""
    real, imag = np.asarray(real), np.asarray(imag)
    ctype = np.complex128 if max(real.dtype.itemsize, imag.dtype.itemsize) == 8 and "f" in (
        real.dtype.kind, imag.dtype.kind) else np.complex64
    return real.astype(ctype) + 1j * imag.astype(ctype)


def read_hdf5(path, *, variable=None, spacing=None, frames=None, **_ignored) -> dict:
    """Read RF (or IQ) frames from a plain HDF5 file: the fields of a :class:`~femreg.io.Frames` (module
    docstring)."""
    import h5py

    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            dsets = _datasets(f)
            pairs = _iq_pairs(dsets)
            name = _choose(path, dsets, variable, pairs)
            ds = dsets[name]
            fields = _compound_iq(ds.dtype)
            if ds.dtype.kind not in "iufc" and fields is None:
                raise fail(path, f"dataset {name!r} is not numeric ({ds.dtype})")
            if ds.size * ds.dtype.itemsize > 1 << 34:
                raise fail(path, f"dataset {name!r} claims {ds.shape} {ds.dtype} (over 16 GiB)")
            arr = ds[()]
            quadrature = pairs.get(name)
            stored = np.dtype(ds.dtype).name
            if fields is not None:          # one compound dataset: the complex samples as two numeric fields
                part = arr[fields[0]]
                stored = f"complex {part.dtype.name} (fields {fields[0]!r}, {fields[1]!r})"
                arr = _as_complex(part, arr[fields[1]])
            elif quadrature is not None:    # the two halves of IQ data as two datasets
                stored = f"complex {arr.dtype.name} (datasets {name!r} + 1j {quadrature!r})"
                arr = _as_complex(arr, dsets[quadrature][()])
            elif ds.dtype.kind == "c":
                stored = f"complex {stored}" if not stored.startswith("complex") else stored
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
    if name in pairs:
        meta["iq_datasets"] = [name, pairs[name]]
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
                       suggestion=spacing_suggestion(attrs, iq=np.iscomplexobj(arr)),
                       frame_shape=arr.shape[-2:])
    origin = check_origin(origin, path, n=2) if origin is not None else (0.0, 0.0)
    return validate_frames(path, arr, sp, origin, meta, frames)
