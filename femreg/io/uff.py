"""UFF (the Ultrasound File Format of the USTB toolbox, HDF5): beamformed frames with their scan.

Layout read (USTB ``uff.write``, MATLAB column-major, so h5py sees every array with its axes reversed): a group per
object with the attribute ``class`` (``uff.beamformed_data``, ``uff.linear_scan``, ``uff.sector_scan``, ...);
numeric datasets carry ``complex`` (0/1), complex ones are a group with ``real`` and ``imag`` datasets.
``beamformed_data/data`` is [pixel x channel x wave x frame] in MATLAB (h5py: (frame, wave, channel, pixel)); the
pixels of a linear scan run down the depth axis first (``z_axis``), then across (``x_axis``), metres.  A sector scan
has ``depth_axis`` (m) and ``azimuth_axis`` (rad) with the pixels of each ray consecutive, and an ``apex``/``origin``.

* Linear scans: frames (n, axial = z, lateral = x), spacing and origin in mm.
* IQ data (complex) are remodulated to RF (:func:`femreg.io.iq.remodulate`) with the stored
  ``modulation_frequency`` and ``c`` (``sound_speed``, default 1540 m/s).
* Sector scans are read (samples (range, angle), ``metadata["geometry"] = "sector"`` with the scan in
  ``metadata["scan"]``) but cannot be registered on a Cartesian pixel grid: the commands that register refuse them.

pyuff-ustb (h5py + numpy only) reads the same files lazily; h5py is used directly because femreg needs three
groups of one object type and h5py is already a dependency (the MATLAB v7.3 reader).
"""
from __future__ import annotations

import numpy as np

from .checks import fail, merge_spacing, validate_frames
from .iq import SOUND_SPEED  # default speed of sound of the remodulation, m/s

__all__ = ["read_uff", "SOUND_SPEED"]


def _cls(node) -> str:
    c = node.attrs.get("class", b"")
    if isinstance(c, np.ndarray):
        c = c.ravel()[0] if c.size else b""
    return c.decode() if isinstance(c, bytes) else str(c)


def _array(path, node, what):
    import h5py

    cplx = node.attrs.get("complex", 0)
    cplx = bool(np.squeeze(cplx)) if np.size(cplx) else False
    if isinstance(node, h5py.Group):
        if not ("real" in node and "imag" in node):
            raise fail(path, f"{what} is a group without real/imag parts")
        return np.asarray(node["real"][...]) + 1j * np.asarray(node["imag"][...])
    a = np.asarray(node[...])
    if cplx and a.dtype.names and {"real", "imag"} <= set(a.dtype.names):
        return a["real"] + 1j * a["imag"]
    return a


def _scalar(path, group, key, default=None):
    if key not in group:
        return default
    v = np.ravel(_array(path, group[key], key))
    if v.size != 1 or not np.isfinite(v[0]):
        raise fail(path, f"{key} must be one finite number, got {v[:4]}")
    return float(np.real(v[0]))


def _axis(path, group, key):
    if key not in group:
        raise fail(path, f"scan has no {key}")
    a = np.ravel(np.real(_array(path, group[key], key))).astype(float)
    if a.size < 2 or not np.all(np.isfinite(a)):
        raise fail(path, f"scan {key} must hold at least 2 finite values, got {a.size}")
    d = np.diff(a)
    if not (np.all(d > 0) and np.ptp(d) <= 1e-3 * abs(d.mean())):
        raise fail(path, f"scan {key} is not uniformly increasing (steps {d.min():.4g}-{d.max():.4g})")
    return a


def _find(path, h5, variable):
    groups = {}

    def visit(name, obj):
        if _cls(obj) == "uff.beamformed_data":
            groups[name] = obj

    h5.visititems(visit)
    if variable is not None:
        if variable not in h5:
            raise fail(path, f"no object {variable!r}; beamformed data: {sorted(groups) or 'none'}")
        node = h5[variable]
        if _cls(node) != "uff.beamformed_data":
            raise fail(path, f"{variable!r} is a {_cls(node) or 'plain'} object, not uff.beamformed_data")
        return variable, node
    if not groups:
        others = sorted({_cls(o) for o in h5.values() if _cls(o)})
        raise fail(path, "no uff.beamformed_data object (holds " + (", ".join(others) or "nothing UFF") + "); "
                   "beamform channel data first (USTB)")
    if len(groups) > 1:
        raise fail(path, f"several beamformed data objects {sorted(groups)}: choose one with variable=/--variable")
    return next(iter(groups.items()))


def _frames_from_data(path, data, n_pix):
    """(n_frames, n_pix) from USTB's [pixel x channel x wave x frame], as h5py sees a MATLAB file (axes reversed:
    (frame, wave, channel, pixel), trailing singletons dropped by MATLAB) or in its own order."""
    shape = data.shape
    if data.ndim == 0 or n_pix not in (shape[0], shape[-1]):
        raise fail(path, f"data shape {shape} has no axis of the scan's {n_pix} pixels")
    pix_last = shape[-1] == n_pix
    d = data if pix_last else np.moveaxis(data, 0, -1)          # (..., pixel)
    lead = d.shape[:-1]
    if len(lead) == 3:              # (frame, wave, channel) or, reversed back, (channel, wave, frame)
        n_frames, per = (lead[0], lead[1] * lead[2]) if pix_last else (lead[2], lead[0] * lead[1])
        if not pix_last:
            d = np.moveaxis(d, 2, 0)
    else:
        big = [n for n in lead if n > 1]
        if len(big) > 1:
            raise fail(path, f"data shape {shape}: cannot tell frames from channels and waves")
        n_frames, per = (big[0] if big else 1), 1
    if per > 1:
        raise fail(path, f"beamformed data has {per} channels x waves per frame; store compounded frames (one "
                         "channel, one wave)")
    return np.asarray(d).reshape(n_frames, n_pix)


def read_uff(path, *, variable=None, spacing=None, frames=None, sound_speed=None, modulation_frequency=None,
             iq_conjugate=False, **_ignored):
    """Read beamformed frames from a UFF file (module docstring) -> :class:`~femreg.io.frames.Frames`;
    ``modulation_frequency`` (MHz) overrides the file's for IQ data."""
    import h5py

    c = SOUND_SPEED if sound_speed is None else float(sound_speed)
    if not (np.isfinite(c) and c > 0):
        raise fail(path, f"sound speed must be > 0 m/s, got {sound_speed!r}")
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        raise fail(path, f"not an HDF5 (UFF) file ({exc})") from None
    with h5:
        name, bf = _find(path, h5, variable)
        if "scan" not in bf:
            raise fail(path, f"{name} has no scan")
        scan = bf["scan"]
        kind = _cls(scan)
        if kind in ("uff.linear_scan", "uff.scan") and "z_axis" in scan:
            ax_a, ax_l = _axis(path, scan, "z_axis"), _axis(path, scan, "x_axis")
            geometry = "linear"
        elif kind == "uff.sector_scan" or "azimuth_axis" in scan:
            ax_a, ax_l = _axis(path, scan, "depth_axis"), _axis(path, scan, "azimuth_axis")
            geometry = "sector"
        else:
            raise fail(path, f"scan of class {kind or '?'} is not supported (linear or sector scans)")
        if "data" not in bf:
            raise fail(path, f"{name} has no data")
        data = _array(path, bf["data"], "data")
        f_mod = _scalar(path, bf, "modulation_frequency", 0.0)
        if modulation_frequency is not None:
            f_mod = 1e6 * float(modulation_frequency)
        fs = _scalar(path, bf, "sampling_frequency")
        fr_rate = _scalar(path, bf, "frame_rate")
    na, nl = ax_a.size, ax_l.size
    d = _frames_from_data(path, data, na * nl)
    # USTB pixel order: depth fastest -> (lateral, axial) in C order
    img = np.ascontiguousarray(d.reshape(-1, nl, na).transpose(0, 2, 1))
    meta = {"format": "uff", "object": name, "geometry": geometry, "scan_class": kind}
    if fs is not None:
        meta["sampling_frequency"] = fs
    if fr_rate is not None:
        meta["frame_rate"] = fr_rate
    if np.iscomplexobj(img):
        if not f_mod > 0:
            raise fail(path, "IQ (complex) data without a modulation_frequency: cannot remodulate to RF")
        from .iq import remodulate

        img, dz_mm, up = remodulate(img, 1e3 * float(np.mean(np.diff(ax_a))), f_mod / 1e6, axial_origin=1e3 * ax_a[0],
                                    sound_speed=c, axis=1, conjugate=bool(iq_conjugate))
        ax_a = ax_a[0] + 1e-3 * dz_mm * np.arange(img.shape[1])
        meta.update(remodulated=True, modulation_frequency=f_mod, sound_speed=c, upsampled=up)
        if geometry == "linear":    # the record read_frames' IQ checks read (femreg.orientation)
            meta["iq"] = {"modulation_frequency_mhz": f_mod / 1e6, "sound_speed": c, "upsampled": up,
                          "conjugate": bool(iq_conjugate), "iq_spacing_mm": dz_mm * up, "iq_samples": int(na)}
    if geometry == "linear":
        file_spacing = (1e3 * float(np.mean(np.diff(ax_a))), 1e3 * float(np.mean(np.diff(ax_l))))
        origin = (1e3 * ax_a[0], 1e3 * ax_l[0])
    else:
        file_spacing = (1e3 * float(np.mean(np.diff(ax_a))), float(np.degrees(np.mean(np.diff(ax_l)))))
        origin = (1e3 * ax_a[0], float(np.degrees(ax_l[0])))
        meta["scan"] = {"range_mm": [1e3 * ax_a[0], 1e3 * ax_a[-1], int(ax_a.size)],
                        "azimuth_deg": [float(np.degrees(ax_l[0])), float(np.degrees(ax_l[-1])), int(ax_l.size)],
                        "axes": "samples (range from the apex, mm; azimuth, degrees); spacing and origin in those"}
    sp = merge_spacing(path, file_spacing, spacing)
    return validate_frames(path, img, sp, origin, meta, frames)


def require_cartesian(fr, what="registration"):
    """InputError for frames of a sector scan (their samples are (range, angle), not a Cartesian grid)."""
    from ..errors import InputError

    if fr.metadata.get("geometry") == "sector":
        s = fr.metadata.get("scan", {})
        raise InputError(f"{fr.source}: a sector scan (range {s.get('range_mm', '?')} mm, azimuth "
                         f"{s.get('azimuth_deg', '?')} deg) needs the convex/sector geometry for {what}, which "
                         "femreg does not have yet; scan-convert the frames to a Cartesian grid first")
    return fr
