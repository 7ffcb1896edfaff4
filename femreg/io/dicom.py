"""DICOM ultrasound images and cine loops (a clinical scanner's export): B-mode frames, not RF.

A scanner's DICOM holds what its screen showed: scan-converted, log-compressed B-mode pixels (often RGB, with text
burned in around the image), calibrated by the ultrasound regions of the US Region Calibration module
(DICOM PS3.3 C.8.5.5, ``SequenceOfUltrasoundRegions``).  The reader:

* reads one file (multi-frame: a cine loop, or one frame) or a folder of single-frame files, sorted by
  ``InstanceNumber`` (:func:`read_dicom_series`);
* crops every frame to the tissue region (``RegionDataType`` 1, 2D; the largest when there are several): rows
  ``RegionLocationMinY0 .. RegionLocationMaxY1`` and columns ``RegionLocationMinX0 .. RegionLocationMaxX1``
  (inclusive), so the burned-in annotations around it are left out;
* spacing: rows are the depth (axial, ``PhysicalDeltaY``), columns the lateral direction (``PhysicalDeltaX``),
  both required in cm (``PhysicalUnitsX/YDirection`` = 3) and returned in mm; without regions the spacing must be
  given (``--spacing``), and the whole image is read;
* origin: from ``ReferencePixelX0/Y0`` (counted from the region's top-left corner, PS3.3 C.8.5.5) and
  ``ReferencePixelPhysicalValueX/Y`` (0 where absent); without a reference pixel the region's first row is at
  depth 0 and its first column at lateral 0, as the other readers' default origin;
* grey levels: MONOCHROME2 as stored, MONOCHROME1 inverted (its 0 is white); RGB, YBR_FULL, YBR_FULL_422 and
  PALETTE COLOR converted to RGB by pydicom, then to luma ``0.299 R + 0.587 G + 0.114 B`` (ITU-R BT.601, the
  weights DICOM's YBR_FULL is defined with, PS3.3 C.7.6.3.1.2: the luma equals the Y the scanner would store,
  and a grey pixel, R = G = B, keeps its value);
* refuses colour: a colour-flow region (``RegionDataType`` 2) over the tissue region, or a tissue region whose
  pixels are coloured (R, G, B apart by more than :data:`COLOUR_LEVELS` of full scale in more than
  :data:`COLOUR_FRACTION` of its pixels) differently from frame to frame: strain from colour-coded pixels is
  meaningless.  Pixels coloured alike in every frame (a body marker, a logo, calipers burned in at one place)
  are an overlay, named in ``metadata["colour"]`` with its fraction (``metadata["overlay_fraction"]``);
* frame rate (Hz) from ``FrameTime`` (ms), ``FrameTimeVector`` or ``CineRate`` into ``metadata["frame_rate"]``
  (as the UFF reader).

The frames are B-mode (no RF carrier): :func:`femreg.register` recognises them as such
(:func:`femreg.orientation.is_envelope`) and registers them without the RF-period checks.
Compressed transfer syntaxes are decoded by the pydicom plugins installed (Pillow, pylibjpeg, GDCM); a missing
decoder is a :class:`~femreg.errors.FileFormatError` naming the packages.  pydicom itself is the ``dicom`` extra
(``pip install 'femreg[dicom]'``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FileFormatError
from .checks import fail, merge_spacing, select_frames

__all__ = ["is_dicom", "read_dicom", "read_dicom_series", "dicom_files", "tissue_region", "DICOM_SUFFIXES",
           "COLOUR_LEVELS", "COLOUR_FRACTION"]

#: File name suffixes read as DICOM (any other file is DICOM when bytes 128-131 are ``DICM``).
DICOM_SUFFIXES = (".dcm", ".dicom")
#: A pixel is coloured when max(R, G, B) - min(R, G, B) exceeds this fraction of full scale (25 of 255 levels:
#: above the chroma noise of lossy YBR_FULL_422 / JPEG grey images, below any colour-flow hue).
COLOUR_LEVELS = 0.1
#: A tissue region with more coloured pixels than this fraction, besides those coloured alike in every frame (an
#: overlay), is refused (a colour-flow box covers far more; in a single frame every coloured pixel counts).
COLOUR_FRACTION = 0.01
_MAX_BYTES = 1 << 34           # as the other readers: a corrupt header, not an image
_UNITS = {0: "none", 1: "percent", 2: "dB", 3: "cm", 4: "seconds", 5: "hertz", 6: "dB/seconds", 7: "cm/sec",
          8: "cm2", 9: "cm2/sec", 10: "cm3", 11: "cm3/sec", 12: "degrees"}
_DATA_TYPES = {0: "none", 1: "tissue", 2: "colour flow", 3: "PW spectral Doppler", 4: "CW spectral Doppler",
               5: "Doppler mean trace", 6: "Doppler mode trace", 7: "Doppler max trace", 8: "volume trace",
               10: "ECG trace", 11: "pulse trace", 12: "phonocardiogram trace", 13: "grey bar", 14: "colour bar",
               15: "integrated backscatter", 16: "area trace", 17: "d(area)/dt", 18: "other physiological input"}
_COLOUR_MSG = ("strain from colour-coded pixels is meaningless (the colours code flow velocity or a map, not "
               "echo): export the loop as grey-scale B-mode, without colour Doppler")


def is_dicom(path) -> bool:
    """True when bytes 128-131 of ``path`` are ``DICM`` (the DICOM file preamble's marker, PS3.10 7.1)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(132)
    except OSError:
        return False
    return head[128:132] == b"DICM"


def _pydicom(path):
    """pydicom, or a FileFormatError naming the extra (a reader's failures are all FileFormatError / InputError)."""
    from ..optional import MissingDependencyError, require

    try:
        return require("pydicom", "dicom", feature="reading DICOM")
    except MissingDependencyError as exc:
        raise fail(path, f"{exc}") from None


def _dataset(path, pydicom, *, stop_before_pixels=False):
    try:
        return pydicom.dcmread(str(path), stop_before_pixels=stop_before_pixels,
                               force=Path(path).suffix.lower() in DICOM_SUFFIXES)
    except pydicom.errors.InvalidDicomError as exc:
        raise fail(path, f"not a DICOM file ({exc})") from None


def _num(item, name, default=None):
    v = item.get(name, None)
    if v is None or (hasattr(v, "__len__") and not isinstance(v, str) and len(v) == 0):
        return default
    try:
        return float(v)
    except (TypeError, ValueError):
        return default


def _region_info(item, k: int) -> dict:
    """One ultrasound region's fields (pixel bounds inclusive, deltas in the file's units), JSON-friendly."""
    g = {name: _num(item, name) for name in (
        "RegionSpatialFormat", "RegionDataType", "RegionLocationMinX0", "RegionLocationMinY0", "RegionLocationMaxX1",
        "RegionLocationMaxY1", "PhysicalUnitsXDirection", "PhysicalUnitsYDirection", "PhysicalDeltaX",
        "PhysicalDeltaY", "ReferencePixelX0", "ReferencePixelY0", "ReferencePixelPhysicalValueX",
        "ReferencePixelPhysicalValueY")}
    g["index"] = k
    g["data_type"] = _DATA_TYPES.get(int(g["RegionDataType"] or 0), f"type {g['RegionDataType']}")
    return g


def _box(r) -> tuple:
    """(x0, y0, x1, y1), inclusive pixel bounds of a region."""
    return (r["RegionLocationMinX0"], r["RegionLocationMinY0"], r["RegionLocationMaxX1"], r["RegionLocationMaxY1"])


def _area(r) -> float:
    x0, y0, x1, y1 = _box(r)
    return (x1 - x0 + 1) * (y1 - y0 + 1)


def _overlap(a, b) -> bool:
    ax0, ay0, ax1, ay1 = _box(a)
    bx0, by0, bx1, by1 = _box(b)
    return not (ax1 < bx0 or bx1 < ax0 or ay1 < by0 or by1 < ay0)


def tissue_region(path, ds) -> tuple:
    """``(region, all regions)`` of a dataset: the largest 2D tissue region of its ``SequenceOfUltrasoundRegions``
    (``(None, [])`` without regions).  FileFormatError for regions without a tissue one, a colour-flow region over
    it, bounds missing or outside the image, units other than cm, deltas not positive."""
    seq = ds.get("SequenceOfUltrasoundRegions", None)
    if not seq:
        return None, []
    regions = [_region_info(item, k) for k, item in enumerate(seq)]
    bounds = ("RegionLocationMinX0", "RegionLocationMinY0", "RegionLocationMaxX1", "RegionLocationMaxY1")
    tissue = [r for r in regions if r["RegionDataType"] == 1 and r["RegionSpatialFormat"] in (None, 1)
              and all(r[b] is not None for b in bounds)]
    if not tissue:
        kinds = ", ".join(r["data_type"] for r in regions)
        raise fail(path, f"no 2D tissue (B-mode) region among its {len(regions)} ultrasound region(s) ({kinds}): "
                         "femreg registers B-mode tissue images")
    region = max(tissue, key=_area)        # first of the largest (a dual display: the left image)
    flow = [r for r in regions if r["RegionDataType"] == 2 and all(r[b] is not None for b in bounds)
            and _overlap(r, region)]
    if flow:
        raise fail(path, f"colour-flow (colour Doppler) region {flow[0]['index']} lies over the tissue region "
                         f"{region['index']}: {_COLOUR_MSG}")
    rows, cols = int(ds.Rows), int(ds.Columns)
    # a last column / row one past the image (an exclusive bound) is a common off-by-one of exporters
    region["RegionLocationMaxX1"] = min(region["RegionLocationMaxX1"], cols - 1.0) if (
        region["RegionLocationMaxX1"] == cols) else region["RegionLocationMaxX1"]
    region["RegionLocationMaxY1"] = min(region["RegionLocationMaxY1"], rows - 1.0) if (
        region["RegionLocationMaxY1"] == rows) else region["RegionLocationMaxY1"]
    if not (0 <= region["RegionLocationMinX0"] <= region["RegionLocationMaxX1"] < cols
            and 0 <= region["RegionLocationMinY0"] <= region["RegionLocationMaxY1"] < rows):
        raise fail(path, f"tissue region {region['index']} (columns {region['RegionLocationMinX0']:g}-"
                         f"{region['RegionLocationMaxX1']:g}, rows {region['RegionLocationMinY0']:g}-"
                         f"{region['RegionLocationMaxY1']:g}) is not inside the {rows} x {cols} image: an image "
                         "resized or cropped after the scanner wrote its calibration, which then no longer applies")
    for axis, what in (("X", "lateral (columns)"), ("Y", "axial (rows)")):
        unit = region[f"PhysicalUnits{axis}Direction"]
        if unit != 3:
            name = _UNITS.get(int(unit), f"code {unit:g}") if unit is not None else "missing"
            raise fail(path, f"tissue region {region['index']}: PhysicalUnits{axis}Direction is {name}, not cm "
                             f"(3): its {what} spacing is not a length; give --spacing DX DY (axial, lateral mm)")
        delta = region[f"PhysicalDelta{axis}"]
        if delta is None or not np.isfinite(delta) or delta <= 0:
            raise fail(path, f"tissue region {region['index']}: PhysicalDelta{axis} = {delta} is not a positive "
                             f"length (a flipped or uncalibrated axis); give --spacing DX DY (axial, lateral mm)")
    return region, regions


def _decoder_check(path, ds):
    """FileFormatError naming the packages when no installed plugin decodes the transfer syntax."""
    ts = ds.file_meta.get("TransferSyntaxUID", None) if hasattr(ds, "file_meta") else None
    if ts is None or not ts.is_compressed:
        return
    from pydicom.pixels import get_decoder

    try:
        dec = get_decoder(ts)
    except NotImplementedError:
        raise fail(path, f"pixel data compressed as {ts.name} ({ts}), which pydicom cannot decode; convert the file "
                         "to an uncompressed transfer syntax (e.g. dcmdjpeg or gdcmconv --raw)") from None
    if not dec.is_available:
        missing = "; ".join(f"{k}: {v}" for k, v in dec.missing_dependencies.items()) if isinstance(
            dec.missing_dependencies, dict) else "; ".join(dec.missing_dependencies)
        raise fail(path, f"pixel data compressed as {ts.name} and no decoder is installed ({missing}); install one, "
                         "e.g. pip install pylibjpeg pylibjpeg-libjpeg pylibjpeg-openjpeg (JPEG, JPEG-LS, JPEG "
                         "2000) or pillow (JPEG baseline, JPEG 2000), or convert the file to an uncompressed "
                         "transfer syntax")


def _frame_rate(ds) -> tuple:
    """``(frames per second, source in words)`` of a cine loop, ``(None, "")`` when the file states none."""
    ft = _num(ds, "FrameTime")
    if ft and ft > 0:
        return 1000.0 / ft, f"FrameTime {ft:g} ms"
    vec = ds.get("FrameTimeVector", None)
    if vec is not None and len(vec) > 1:
        steps = np.asarray([float(v) for v in vec[1:]], float)
        if np.all(steps > 0):
            return 1000.0 / float(np.mean(steps)), f"FrameTimeVector, mean {np.mean(steps):g} ms"
    cr = _num(ds, "CineRate")
    if cr and cr > 0:
        return cr, f"CineRate {cr:g}"
    return None, ""


def _grey(frame, photometric, bits_stored, signed):
    """One decoded frame (rows, cols[, 3]) as float32 grey levels and its coloured pixels ((rows, cols) bool,
    None for grey frames)."""
    if frame.ndim == 3:
        rgb = frame.astype(np.float32)
        full = float(2 ** bits_stored - 1)
        chroma = rgb.max(axis=2) - rgb.min(axis=2)
        luma = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]
        return luma.astype(np.float32), chroma > COLOUR_LEVELS * full
    g = frame.astype(np.float32)
    if photometric == "MONOCHROME1":     # 0 is white: invert within the stored range
        lo, hi = (-(2 ** (bits_stored - 1)), 2 ** (bits_stored - 1) - 1) if signed else (0, 2 ** bits_stored - 1)
        g = np.float32(lo + hi) - g
    return g, None


class _ColourCheck:
    """Coloured pixels of the tissue region, frame by frame.  Pixels coloured alike in every frame (a logo, a
    body marker, a focus marker, calipers: overlays burned in at one place) are an overlay, not colour Doppler,
    whose colours change between frames with the flow; more than :data:`COLOUR_FRACTION` of the region coloured
    otherwise (or at all, in a single frame, where the two cannot be told apart) is refused."""

    def __init__(self, path, where, full):
        self.path, self.where = path, where
        self.tol = 0.5 * COLOUR_LEVELS * full      # lossy (JPEG) frames repeat an overlay only approximately
        self.first = self.static = None
        self.n = 0

    def add(self, k, crop, coloured, n_frames):
        if coloured is None:
            return
        self.n += 1
        if self.first is None:
            self.first, self.static = np.array(crop, np.float32), coloured.copy()
            changing = 0.0 if n_frames > 1 else float(np.mean(coloured))
        else:
            same = coloured & self.static & np.all(np.abs(crop - self.first) <= self.tol, axis=-1)
            changing = float(np.mean(coloured & ~same))
            self.static &= same
        if changing > COLOUR_FRACTION:
            raise fail(self.path, f"frame {k}: {100 * changing:.1f} % of {self.where} pixels are coloured (R, G, B "
                                  f"more than {100 * COLOUR_LEVELS:g} % of full scale apart)"
                                  + ("" if n_frames == 1 else ", differently from frame to frame")
                                  + f": colour Doppler or a colour map; {_COLOUR_MSG}")

    def overlay_fraction(self) -> float:
        """Fraction of the region coloured alike in every frame (0 for a single frame or grey frames)."""
        return float(np.mean(self.static)) if self.static is not None and self.n > 1 else 0.0


def read_dicom(path, *, spacing=None, frames=None, **_ignored) -> dict:
    """Frames of one DICOM file (see the module docstring); returns the fields of a :class:`femreg.io.Frames`
    through :func:`femreg.io.checks.validate_frames`.

    ``spacing`` (dx, dy) mm replaces the region's (None entries keep it); ``metadata["header_spacing"]`` keeps
    the region's, which :func:`femreg.io.read_frames` compares with a given spacing.
    """
    from .checks import validate_frames

    path = Path(path)
    pydicom = _pydicom(path)
    ds = _dataset(path, pydicom)
    if "PixelData" not in ds:
        if not is_dicom(path):
            raise fail(path, "not a DICOM image (no 'DICM' marker at byte 128, and no pixel data read)")
        raise fail(path, "DICOM file without pixel data (a DICOMDIR, a report or a presentation state?)")
    for name in ("Rows", "Columns", "BitsStored"):
        if name not in ds and not (name == "BitsStored" and "BitsAllocated" in ds):
            raise fail(path, f"DICOM image without {name}")
    _decoder_check(path, ds)
    photometric = str(ds.get("PhotometricInterpretation", "MONOCHROME2")).strip().upper()
    samples = int(ds.get("SamplesPerPixel", 1))
    n_total = int(ds.get("NumberOfFrames", 1) or 1)
    region, regions = tissue_region(path, ds)
    idx = select_frames(path, np.arange(n_total), frames)
    rows, cols = int(ds.Rows), int(ds.Columns)
    if region is not None:
        r0, r1 = int(region["RegionLocationMinY0"]), int(region["RegionLocationMaxY1"]) + 1
        c0, c1 = int(region["RegionLocationMinX0"]), int(region["RegionLocationMaxX1"]) + 1
    else:
        r0, r1, c0, c1 = 0, rows, 0, cols
    bits = int(ds.get("BitsStored", ds.get("BitsAllocated", 8)))
    signed = int(ds.get("PixelRepresentation", 0)) == 1
    if region is not None:      # the spacing first: a missing one is said before any pixel is decoded
        header = (10.0 * region["PhysicalDeltaY"], 10.0 * region["PhysicalDeltaX"])
        sp = merge_spacing(path, header, spacing)
    else:
        sp = merge_spacing(path, None, spacing,
                           required_msg="the DICOM file has no SequenceOfUltrasoundRegions, the calibration of a "
                                        "scanner's ultrasound image")
    from pydicom.pixels import apply_color_lut, iter_pixels

    if idx.size * (r1 - r0) * (c1 - c0) * 4 > _MAX_BYTES:
        raise fail(path, f"header claims {idx.size} frames of {rows} x {cols}: over 16 GiB as float32")
    out = np.empty((idx.size, r1 - r0, c1 - c0), np.float32)
    colour = _ColourCheck(path, "the tissue region's" if region is not None else "the image's (no region to crop to)",
                          2.0 ** (8 if photometric == "PALETTE COLOR" else bits) - 1)
    try:
        for k, frame in enumerate(iter_pixels(ds, indices=[int(i) for i in idx])):
            if photometric == "PALETTE COLOR":
                frame = apply_color_lut(frame, ds)
                bits = 8 * frame.dtype.itemsize
            crop = frame[r0:r1, c0:c1]
            g, coloured = _grey(crop, photometric, bits, signed)
            colour.add(int(idx[k]), crop, coloured, idx.size)
            out[k] = g
    except FileFormatError:
        raise
    except (RuntimeError, NotImplementedError, ValueError) as exc:
        raise fail(path, f"cannot decode the pixel data ({type(exc).__name__}: {exc})") from None
    rate, rate_from = _frame_rate(ds)
    stored = f"{'int' if signed else 'uint'}{bits}"
    meta = {"format": "dicom", "stored_dtype": stored if samples == 1 else f"{stored} x {samples} samples",
            "photometric": photometric,
            "transfer_syntax": str(ds.file_meta.TransferSyntaxUID.name) if "TransferSyntaxUID" in ds.file_meta
            else "", "image_size": [rows, cols], "frames_in_file": n_total}
    if samples == 3 or photometric == "PALETTE COLOR":
        overlay = colour.overlay_fraction()
        fixed = (f" but for a coloured overlay fixed on the screen ({100 * overlay:.1f} % of it: markers, text, a "
                 "logo), which does not move with the tissue: leave it out with --roi")
        meta["colour"] = (f"{photometric} converted to luma 0.299 R + 0.587 G + 0.114 B (ITU-R BT.601); the "
                          "tissue region is grey" + ("" if overlay < 1e-4 else fixed))
        if overlay >= 1e-4:
            meta["overlay_fraction"] = overlay
    elif photometric == "MONOCHROME1":
        meta["colour"] = "MONOCHROME1 inverted (its 0 is white)"
    for name in ("Modality", "Manufacturer", "ManufacturerModelName", "TransducerData", "InstanceNumber"):
        if ds.get(name, None) not in (None, ""):
            meta[name[0].lower() + name[1:]] = str(ds.get(name))
    origin = (0.0, 0.0)
    if region is not None:
        dy_cm, dx_cm = region["PhysicalDeltaY"], region["PhysicalDeltaX"]
        meta["header_spacing"] = list(header)
        meta["spacing_source"] = (f"DICOM ultrasound region {region['index']} of {len(regions)}: axial PhysicalDeltaY "
                                  f"{dy_cm:g} cm per row, lateral PhysicalDeltaX {dx_cm:g} cm per column")
        meta["region"] = {"index": region["index"], "of": len(regions), "data_type": region["data_type"],
                          "rows": [r0, r1 - 1], "columns": [c0, c1 - 1]}
        meta["crop"] = (f"rows {r0}-{r1 - 1}, columns {c0}-{c1 - 1} of the {rows} x {cols} image (tissue region "
                        f"{region['index']}; the rest, annotations included, left out)")
        ax = []
        for ref_pixel, ref_value, delta in (("ReferencePixelY0", "ReferencePixelPhysicalValueY", dy_cm),
                                            ("ReferencePixelX0", "ReferencePixelPhysicalValueX", dx_cm)):
            p, v = region[ref_pixel], region[ref_value]
            # ReferencePixelX0/Y0 count from the region's top-left corner (PS3.3 C.8.5.5; a Philips export's
            # tissue region has its lateral 0 there at the region's centre column, its ECG region -MinX0, -MinY0)
            ax.append(10.0 * ((v or 0.0) - p * delta) if p is not None else 0.0)
        origin = tuple(ax)
        if region["ReferencePixelY0"] is not None or region["ReferencePixelX0"] is not None:
            meta["origin_source"] = "from the region's ReferencePixelX0/Y0 and their physical values"
    else:
        meta["crop"] = (f"none: no SequenceOfUltrasoundRegions, the whole {rows} x {cols} image is read (annotations "
                        "included: --roi registers the image part)")
        meta["spacing_source"] = "given (--spacing); the DICOM file states none"
    if rate is not None:
        meta["frame_rate"] = rate
        meta["frame_rate_source"] = rate_from
    meta["data"] = "B-mode (scan-converted, log-compressed display pixels), not RF"
    return validate_frames(path, out, sp, origin, meta, None)


def dicom_files(folder) -> list:
    """The DICOM files of a folder: ``.dcm`` / ``.dicom`` files, and files without a known extension (none, or a
    UID's digits) whose bytes 128-131 are ``DICM``; ``DICOMDIR`` left out."""
    from .checks import FORMATS

    out = []
    for p in Path(folder).iterdir():
        if not p.is_file() or p.name.startswith(".") or p.name.upper() == "DICOMDIR":
            continue
        suffix = p.suffix.lower()
        if suffix in DICOM_SUFFIXES or (suffix not in FORMATS and is_dicom(p)):
            out.append(p)
    return out


def read_dicom_series(folder, files, *, spacing=None, frames=None, **_ignored) -> dict:
    """Frames of a folder of DICOM files (one frame or loop each), in ``InstanceNumber`` order (file names in
    natural order where it is missing or tied); one series only, every file of one frame size and spacing."""
    from .checks import natural_key, validate_frames

    folder = Path(folder)
    pydicom = _pydicom(folder)
    heads = []
    for f in files:
        ds = _dataset(f, pydicom, stop_before_pixels=True)
        inst = ds.get("InstanceNumber", None)
        heads.append((f, ds, int(inst) if inst not in (None, "") else None))
    series = sorted({str(ds.get("SeriesInstanceUID", "")) for _, ds, _ in heads})
    if len(series) > 1:
        names = ", ".join(s or "(none)" for s in series[:3]) + (", ..." if len(series) > 3 else "")
        raise fail(folder, f"the folder holds {len(series)} DICOM series ({names}): move one series' files into a "
                           "folder of their own")
    big = 10 ** 9
    heads.sort(key=lambda h: (h[2] if h[2] is not None else big, natural_key(h[0].name)))
    parts = [read_dicom(f, spacing=spacing) for f, _, _ in heads]
    first = parts[0]
    for (f, _, _), part in zip(heads[1:], parts[1:]):
        if part["frames"].shape[1:] != first["frames"].shape[1:]:
            raise fail(f, f"frame shape {part['frames'].shape[1:]} differs from {heads[0][0].name}'s "
                          f"{first['frames'].shape[1:]}")
        if not np.allclose(part["spacing"], first["spacing"], rtol=1e-6):
            raise fail(f, f"spacing {part['spacing']} differs from {heads[0][0].name}'s {first['spacing']}")
    stack = np.concatenate([p["frames"] for p in parts], axis=0)
    meta = {**first["metadata"], "format": "directory of dicom", "files": [h[0].name for h in heads],
            "order": "InstanceNumber" if all(h[2] is not None for h in heads) else "InstanceNumber, then file name"}
    meta.pop("instanceNumber", None)
    meta.pop("frames_in_file", None)
    return validate_frames(folder, stack, first["spacing"], first["origin"], meta, frames)
