"""Where the echo is in an RF volume (axial, lateral, elevational) = (x, y, z): the box of usable echo, and
volume registration inside it -- :mod:`femreg.echo` one dimension up, with its rules and constants.

:func:`find_echo_volume` reads the level of the envelope against the receiver's noise floor as
:func:`femreg.echo.find_echo` does in a frame:

* voxels' lines (x at one (y, z)), lateral planes (one y) and elevational planes (one z) whose RF is zero
  throughout hold no signal (dead planes at the edges of a swept probe, zero-padded samples);
* the depth profile: the median over about :data:`femreg.echo.PROFILE_LINES` lines spread over the whole
  (y, z) aperture of each row's envelope power, smoothed over :data:`femreg.echo.SMOOTH_PERIODS` RF periods; its
  floor and echo percentiles and the hysteresis of :data:`femreg.echo.SEED_SNR_DB` / :data:`femreg.echo.MIN_SNR_DB`
  echo SNR give the depth range;
* on the rows kept, the lateral profile (median RF power of each lateral plane over depth and elevation) and then,
  on the lines kept, the elevational profile (of each elevational plane over depth and the lateral lines kept),
  both against the depth profile's floor;
* the veto from the pair: a strip whose envelope still matches the other volume (best NCC over small shifts at
  least :data:`femreg.echo.ECHO_NCC`, on up to :data:`VETO_PLANES` elevational planes of it) holds echo that
  moves with the tissue and is kept;
* saturation: slabs at the box's faces with more than :data:`femreg.echo.CLIP_ROW_FRACTION` clipped samples.

Only slabs at the faces can be left out (the mesh is a box).  :func:`crop_for_volume` turns the detection, or a
user's ``roi`` (x0, x1, y0, y1, z0, z1) / ``depth`` (d0, d1) mm, into the crop of the volumes that
:func:`femreg.volume.register_volume` and :func:`femreg.volume.track_volume` register; their results keep the
full volume's voxel grid (NaN outside the mesh) and say what was left out (``excluded``, ``roi``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .echo import (CLIP_ROW_FRACTION, DEAD_LEVEL, ECHO_NCC, MIN_RANGE_DB, MIN_SNR_DB, PROFILE_LINES, PROFILE_ROWS,
                   RF_TO_ENVELOPE_POWER, SMOOTH_LINES, SMOOTH_PERIODS, VETO_PERIODS, _clipped, _echo_run,
                   _AXES, _echo_span, _extent_text, _live_span, _margin_pixels, _profile, _span, _strip_ncc, _why,
                   Crop, crop_request, rf_like)
from .errors import InputError
from .speckle import envelope, rf_period

__all__ = ["EchoBox", "find_echo_volume", "crop_for_volume", "region_from_mm_volume", "VolumeCrop", "route_volume",
           "unmatched_crop_volume", "registered_crop_volume", "VETO_PLANES"]

#: Elevational planes (at most) a strip's frame-to-frame veto is measured on (and the block matching of
#: :func:`unmatched_crop_volume`).
VETO_PLANES = 8
#: Depth step (mm) at which :func:`unmatched_crop_volume` samples the start's displacement (linear between).
STEP_MM = 0.25


@dataclass
class EchoBox:
    """The box of usable echo of a volume (pair) (:func:`find_echo_volume`).

    ranges : ((a, b), (c, d), (e, f)) half-open voxel index ranges along x, y, z; ``shape``, ``spacing``,
    ``origin`` the volume's grid (mm).  ``excluded``: what was left out and why (None: nothing); ``floor_db`` /
    ``echo_db`` the depth profile's noise floor and echo level (dB, NaN where not measured).
    """

    ranges: tuple
    shape: tuple
    spacing: tuple
    origin: tuple
    excluded: str | None = None
    floor_db: float = float("nan")
    echo_db: float = float("nan")

    @property
    def full(self) -> bool:
        return all(tuple(r) == (0, n) for r, n in zip(self.ranges, self.shape))

    @property
    def roi_mm(self) -> tuple:
        """(x0, x1, y0, y1, z0, z1) mm: the box's outer voxel-cell edges."""
        out = []
        for (lo, hi), o, s in zip(self.ranges, self.origin, self.spacing):
            out += [o + (lo - 0.5) * s, o + (hi - 0.5) * s]
        return tuple(float(v) for v in out)


def find_echo_volume(reference, moving=None, *, spacing, origin=(0.0, 0.0, 0.0)) -> EchoBox:
    """Detect the box of usable echo of an RF volume (pair) (module docstring).

    Parameters
    ----------
    reference, moving : (n_x, n_y, n_z) RF volumes; ``moving`` (optional) adds the veto and its own clipping.
    spacing, origin : (3,) mm

    Returns
    -------
    EchoBox (``excluded`` None when the whole volume holds echo).
    """
    from .voxels import validate_spacing_3d, validate_volume

    ref = validate_volume(reference, "reference volume")
    mov = None if moving is None else validate_volume(moving, "moving volume")
    if mov is not None and mov.shape != ref.shape:
        raise InputError(f"volume shape mismatch: reference {ref.shape} vs moving {mov.shape}")
    spacing, origin = validate_spacing_3d(spacing, origin)
    return _find_echo_volume(ref, mov, spacing, origin)


def _find_echo_volume(ref, mov, spacing, origin) -> EchoBox:
    """:func:`find_echo_volume` on validated volumes."""
    nx, ny, nz = ref.shape
    sp = tuple(float(s) for s in spacing)
    org = tuple(float(o) for o in origin)
    full = EchoBox(((0, nx), (0, ny), (0, nz)), (nx, ny, nz), sp, org)
    ref2 = ref.reshape(nx, -1)
    if not rf_like(ref2):
        return full
    mag = np.abs(ref)
    thr = DEAD_LEVEL * float(np.max(mag))
    live_yz = np.max(mag, axis=0) > thr                  # lines with any signal
    live_y, live_z = live_yz.any(axis=1), live_yz.any(axis=0)
    live_x = np.max(mag.reshape(nx, -1)[:, live_yz.ravel()], axis=1) > thr
    lines = np.flatnonzero(live_yz.ravel())
    lines = lines[::max(1, lines.size // PROFILE_LINES)]     # spread over the whole (y, z) aperture
    row_med = np.median(envelope(ref2[:, lines]) ** 2, axis=1)
    period = rf_period(ref2[:, lines], sp[:2])
    w = int(max(3, round(SMOOTH_PERIODS * period / sp[0])))
    row_db, floor, echo = _profile(row_med, live_x, w)
    reasons = []

    def block(vol, ys, zs):
        """(n_x, len(zs) len(ys)) lines of ``vol``, y contiguous within each elevational plane."""
        return np.ascontiguousarray(vol[:, ys][:, :, zs].transpose(0, 2, 1)).reshape(nx, -1)

    def veto(rows, ys, zs):
        """True when the strip (rows, lines ys, planes zs) still matches the other volume."""
        if mov is None or rows[1] - rows[0] < 2 or ys.size < 1 or zs.size < 1:
            return False
        zs = zs[np.unique(np.linspace(0, zs.size - 1, min(zs.size, VETO_PLANES)).round().astype(int))]
        ea, eb = envelope(block(ref, ys, zs)), envelope(block(mov, ys, zs))
        depth = org[0] + rows[1] * sp[0]
        max_shift = int(np.ceil(max(3.0 * period, 0.05 * abs(depth)) / sp[0]))
        step = max(1, int(round(period / (2.0 * sp[0]))))
        chunk = max(8, int(round(VETO_PERIODS * period / (step * sp[0]))))
        return _strip_ncc(ea, eb, rows, (0, ea.shape[1]), max_shift, step, chunk=chunk) >= ECHO_NCC

    # depth
    has_floor = echo - floor >= MIN_RANGE_DB
    (a, b) = _echo_run(row_db, floor, max(w, nx // 20), live_x)[0] if has_floor else _live_span(live_x)
    if b <= a:
        a, b = _live_span(live_x)
    at = f" at {_echo_span(row_db, echo, org[0], sp[0])}"
    all_y, all_z = np.flatnonzero(live_y), np.flatnonzero(live_z)
    if a > 0 and has_floor and veto((0, a), all_y, all_z):
        a = _live_span(live_x)[0]
    if a > 0:
        reasons.append(f"depth above {org[0] + (a - 0.5) * sp[0]:.1f} mm "
                       + _why(has_floor and live_x[:a].any(), echo, floor, at))
    if b < nx and has_floor and veto((b, nx), all_y, all_z):
        b = _live_span(live_x)[1]
    if b < nx:
        reasons.append(f"depth below {org[0] + (b - 0.5) * sp[0]:.1f} mm "
                       + _why(has_floor and live_x[b:].any(), echo, floor, at))
    # lateral lines over the rows kept, then elevational planes over the rows and lines kept; the median RF power
    # of a plane (Gaussian RF: the envelope's median power over RF_TO_ENVELOPE_POWER) needs no envelope
    q = max(1, (b - a) // PROFILE_ROWS)
    sub = ref[a:b:q]

    def side(med, live, n, what, names, o, s, strip):
        prof, pfloor, pecho = _profile(med * RF_TO_ENVELOPE_POWER, live, SMOOTH_LINES)
        if has_floor:
            pfloor = floor
        ok = pecho - pfloor >= MIN_RANGE_DB
        (c0, c1) = _echo_run(prof, pfloor, max(SMOOTH_LINES, n // 20), live)[0] if ok else _live_span(live)
        if c1 <= c0:
            c0, c1 = _live_span(live)
        for lo, hi, name in ((0, c0, names[0]), (c1, n, names[1])):
            if hi <= lo:
                continue
            if ok and veto((a, b), *strip(lo, hi)):
                c0, c1 = (_live_span(live)[0], c1) if name == names[0] else (c0, _live_span(live)[1])
                lo, hi = (0, c0) if name == names[0] else (c1, n)
                if hi > lo:
                    reasons.append(f"{what} at {_span(lo, hi, o, s)} ({name}) " + _why(False, 0, 0))
            else:
                reasons.append(f"{what} at {_span(lo, hi, o, s)} ({name}) "
                               + _why(ok and live[lo:hi].any(), pecho, pfloor))
        return c0, c1

    live_y = live_y & (np.max(mag[a:b], axis=(0, 2)) > thr)
    y_med = np.median(sub[:, :, live_z] ** 2, axis=(0, 2)) if live_z.any() else np.zeros(ny)
    c0, c1 = side(y_med, live_y, ny, "lateral lines", ("left", "right"), org[1], sp[1],
                  lambda lo, hi: (np.arange(lo, hi), all_z))
    live_z = live_z & (np.max(mag[a:b, c0:c1], axis=(0, 1)) > thr)
    z_med = np.median(sub[:, c0:c1] ** 2, axis=(0, 1))
    e0, e1 = side(z_med, live_z, nz, "elevational planes", ("front", "back"), org[2], sp[2],
                  lambda lo, hi: (np.arange(c0, c1), np.arange(lo, hi)))
    box = [[a, b], [c0, c1], [e0, e1]]
    # saturation at the box's faces
    clip = _clipped([mag] if mov is None else [mag, np.abs(mov)])
    if clip is not None:
        before = [list(r) for r in box]
        for ax in range(3):
            others = tuple(ax2 for ax2 in range(3) if ax2 != ax)

            def frac(i, ax=ax, others=others):
                sl = [slice(*box[k]) for k in range(3)]
                sl[ax] = i
                return float(np.mean(clip[tuple(sl)]))

            while box[ax][0] < box[ax][1] and frac(box[ax][0]) > CLIP_ROW_FRACTION:
                box[ax][0] += 1
            while box[ax][1] > box[ax][0] and frac(box[ax][1] - 1) > CLIP_ROW_FRACTION:
                box[ax][1] -= 1
        total = float(np.mean(clip))
        for ax, what in enumerate(("depth", "lateral lines", "elevational planes")):
            for lo, hi in ((before[ax][0], box[ax][0]), (box[ax][1], before[ax][1])):
                if hi > lo:
                    reasons.append(f"{what} {_span(lo, hi, org[ax], sp[ax])} excluded: saturated (more than "
                                   f"{CLIP_ROW_FRACTION:.0%} of the samples clipped; {total:.1%} of the volume)")
        inner = clip[box[0][0]:box[0][1], box[1][0]:box[1][1], box[2][0]:box[2][1]]
        k = np.flatnonzero(np.mean(inner, axis=(1, 2)) > CLIP_ROW_FRACTION) if inner.size else np.array([], int)
        if k.size:
            reasons.append(f"saturated rows at {_span(box[0][0] + int(k[0]), box[0][0] + int(k[-1]) + 1, org[0], sp[0])}"
                           f" kept (inside the echo box)")
    return EchoBox(tuple(tuple(int(v) for v in r) for r in box), (nx, ny, nz), sp, org, "; ".join(reasons) or None,
                   floor, echo)


def region_from_mm_volume(shape, spacing, origin, *, roi=None, depth=None) -> EchoBox:
    """The voxel box of a user's ``roi`` (x0, x1, y0, y1, z0, z1) or ``depth`` (d0, d1) mm: the voxels whose centres
    lie inside it.  :class:`InputError` naming the volume's extent when it leaves the volume or holds fewer than
    2 voxels along an axis."""
    if roi is not None and depth is not None:
        raise InputError("give roi or depth, not both (depth (d0, d1) is roi (d0, d1, y0, y1, z0, z1) over the "
                         "whole aperture)")
    what = "roi" if roi is not None else "depth"
    val = roi if roi is not None else depth
    try:
        v = np.asarray(val, float).ravel()
    except (TypeError, ValueError):
        v = np.array([np.nan])
    need = 6 if roi is not None else 2
    if v.size != need or not np.all(np.isfinite(v)) or np.any(v[0::2] >= v[1::2]):
        form = "(x0, x1, y0, y1, z0, z1) mm with x0 < x1, y0 < y1 and z0 < z1" if need == 6 else \
            "(d0, d1) mm with d0 < d1"
        raise InputError(f"the {what} of a volume must be {form}, got {val!r}")
    sp, org = np.asarray(spacing, float), np.asarray(origin, float)
    lo = org - 0.5 * sp
    hi = lo + np.asarray(shape, float) * sp
    tol = 1e-6 * sp
    box = v if need == 6 else np.array([v[0], v[1], lo[1], hi[1], lo[2], hi[2]])
    if np.any(box[0::2] < lo - tol) or np.any(box[1::2] > hi + tol):
        raise InputError(f"{what} {tuple(float(x) for x in v)} mm leaves the volume; the volume's extent is "
                         f"{_extent_text(shape, spacing, origin)}")
    idx = []
    for ax in range(3):           # voxel centres c_i = origin + i * spacing inside [box_2ax, box_2ax+1]
        i0 = int(np.ceil((box[2 * ax] - org[ax]) / sp[ax] - 1e-6))
        i1 = int(np.floor((box[2 * ax + 1] - org[ax]) / sp[ax] + 1e-6)) + 1
        idx.append((max(0, i0), min(int(shape[ax]), i1)))
    if any(i1 - i0 < 2 for i0, i1 in idx):
        raise InputError(f"{what} {tuple(float(x) for x in v)} mm holds fewer than 2 voxels along an axis; the "
                         f"volume's extent is {_extent_text(shape, spacing, origin)}")
    region = EchoBox(tuple(idx), tuple(int(s) for s in shape), tuple(float(s) for s in sp),
                     tuple(float(s) for s in org))
    x0, x1, y0, y1, z0, z1 = region.roi_mm
    region.excluded = (f"outside the given {what} x {x0:.1f}-{x1:.1f} mm, y {y0:.1f}-{y1:.1f} mm, "
                       f"z {z0:.1f}-{z1:.1f} mm excluded")
    return region


class VolumeCrop(Crop):
    """The volumes cut to a box, and how to put a result registered there back on the full voxel grid (the 3D
    :class:`femreg.echo.Crop`: a detected box is cut as it is, the mesh margin inside it; a given one is widened by
    the margin where the volume has it, so that the mesh covers it).  ``slices`` (3,), ``origin`` the crop's voxel
    [0, 0, 0] centre (mm), ``region`` the :class:`EchoBox`, ``seconds`` the detection's time."""

    def __init__(self, region: EchoBox, margin_px, pad: bool, seconds=0.0):
        self.region = region
        self.seconds = float(seconds)
        sl = []
        for k, ((a, b), n, mp) in enumerate(zip(region.ranges, region.shape, margin_px)):
            p = int(mp) if pad else 0
            s = slice(max(0, a - p), min(int(n), b + p))
            if s.stop - s.start - 2 * int(mp) < 1:
                lo, hi = region.roi_mm[2 * k], region.roi_mm[2 * k + 1]
                raise InputError(f"the {'region' if pad else 'echo box'} {lo:.2f} to {hi:.2f} mm along "
                                 f"{_AXES[k]} is too small for a mesh inside the margin ({int(mp)} voxels)"
                                 + (f": {region.excluded}" if region.excluded else ""))
            sl.append(s)
        self.slices = tuple(sl)
        self.origin = tuple(region.origin[k] + sl[k].start * region.spacing[k] for k in range(3))

    @staticmethod
    def _clear_grids(res):
        res._grids = {}


def crop_for_volume(reference, moving, spacing, origin=(0.0, 0.0, 0.0), *, roi="auto", depth=None, mesh=None,
                    margin=None, initial=None, offset=None) -> VolumeCrop | None:
    """The crop :func:`femreg.volume.register_volume` / :func:`femreg.volume.track_volume` register on, or None
    for the whole volumes (the 3D :func:`femreg.echo.crop_for`).

    ``roi``: "auto" (default) detects the echo box (:func:`find_echo_volume`), None keeps the whole volumes,
    (x0, x1, y0, y1, z0, z1) mm a given box; ``depth`` (d0, d1) mm a given depth range over the whole aperture (a
    given box or depth disables the detection).  With a user ``mesh`` there is no crop (a given roi or depth is
    then an error), nor for the detection when ``initial`` or ``offset`` is a nodal vector of the default mesh.
    The detection changes nothing (None) when what it excludes lies within the mesh margin."""
    from .voxels import DEFAULT_MARGIN_3D, validate_spacing_3d, validate_volume

    given = crop_request(roi, depth, mesh, initial, offset, volume=True)
    if given is None:
        return None
    t = time.perf_counter()
    ref = validate_volume(reference, "reference volume")
    mov = validate_volume(moving, "moving volume")
    if ref.shape != mov.shape:
        raise InputError(f"volume shape mismatch: reference {ref.shape} vs moving {mov.shape}")
    spacing, origin = validate_spacing_3d(spacing, origin)
    mp = _margin_pixels(margin, spacing, DEFAULT_MARGIN_3D)
    if given:
        region = region_from_mm_volume(ref.shape, spacing, origin, roi=None if isinstance(roi, str) else roi,
                                       depth=depth)
        return VolumeCrop(region, mp, True, time.perf_counter() - t)
    if not rf_like(ref.reshape(ref.shape[0], -1)):
        return None
    region = _find_echo_volume(ref, mov, spacing, origin)
    if all(r[0] <= m and r[1] >= n - m for r, n, m in zip(region.ranges, ref.shape, mp)):
        return None                  # nothing beyond the margin the mesh leaves out anyway
    return VolumeCrop(region, mp, False, time.perf_counter() - t)


def route_volume(register_volume, args: dict):
    """The call :func:`femreg.volume.register_volume` hands on before its own stages: the echo box or a given
    roi / depth (:func:`crop_for_volume`), registered by ``register_volume`` on the crop and widened to the full
    voxel grid.  ``args``: its arguments (``ignored`` holding roi / depth).  Returns the result, or None when
    the volumes are registered whole."""
    extra = dict(args.get("ignored") or {})
    kw = {k: v for k, v in args.items() if k not in ("reference_image", "moving_image", "ignored")}
    roi, depth = extra.pop("roi", "auto"), extra.pop("depth", None)
    crop = crop_for_volume(args["reference_image"], args["moving_image"], kw["spacing"], kw["origin"], roi=roi,
                           depth=depth, mesh=kw["mesh"], margin=kw["margin"], initial=kw["initial"],
                           offset=kw["offset"])
    return None if crop is None else registered_crop_volume(register_volume, crop, args)


def registered_crop_volume(register_volume, crop, args: dict):
    """``register_volume`` (:func:`femreg.volume.register_volume`; ``args`` its arguments, ``ignored`` holding roi /
    depth) on the volumes cut to ``crop`` (:class:`VolumeCrop`), widened to the full voxel grid."""
    kw = {k: v for k, v in args.items() if k not in ("reference_image", "moving_image", "ignored")}
    kw.update(args.get("ignored") or {}, origin=crop.origin, roi=None, depth=None)
    return crop.widen(register_volume(*crop.frames(args["reference_image"], args["moving_image"]), **kw))


def unmatched_crop_volume(reference, moving, start, mesh, spacing, origin, margin=None) -> VolumeCrop | None:
    """The volumes cut above the depth where they stop matching after the start has searched out the motion, or
    None: :func:`femreg.echo.unmatched_crop` (its rule and constants: noise a time-gain compensation lifts to the
    echo's level at depth) on the block matching of up to :data:`VETO_PLANES` elevational planes.

    ``reference``, ``moving``: (n_x, n_y, n_z) RF volumes (validated); ``start``: the registration's start, nodal
    u (3 n_nodes,) of the tensor hexahedral ``mesh`` (:func:`femreg.volume.coarse_to_fine`); ``spacing``,
    ``origin`` mm; ``margin``: the mesh margin (mm, default :data:`femreg.voxels.DEFAULT_MARGIN_3D`).  On each
    plane z the reference envelope is block-matched (:func:`femreg.blockmatch.block_match`, the windows and
    search of the 2D pyramid's local search, :func:`femreg.pyramid.image_settings`) against the moving envelope
    read at (x, y, z) + u(x, y, z); the planes' windows side by side make the rows whose median NCC the 2D rule
    reads.  Only the depth can be cut: rows of windows at the box's bottom."""
    from scipy import ndimage
    from scipy.interpolate import interp1d

    from .blockmatch import BlockMatchResult, block_match
    from .echo import unmatched_crop
    from .pyramid import image_settings
    from .volume_fields import HexLocator
    from .voxels import DEFAULT_MARGIN_3D

    t = time.perf_counter()
    ref, mov = np.asarray(reference, float), np.asarray(moving, float)
    nx, ny, nz = ref.shape
    sp, org = np.asarray(spacing, float), np.asarray(origin, float)
    zs = np.unique(np.linspace(0, nz - 1, min(nz, VETO_PLANES)).round().astype(int))
    _, settings = image_settings(ref[:, :, nz // 2], sp[:2])
    # u of the start on every plane, sampled every STEP_MM of depth and read linearly between (the start is
    # trilinear on elements of about 2 mm)
    rows = np.unique(np.r_[np.arange(0, nx, max(1, int(STEP_MM / sp[0]))), nx - 1])
    Xs, Y = np.meshgrid(org[0] + sp[0] * rows, org[1] + sp[1] * np.arange(ny), indexing="ij")
    loc = HexLocator(mesh)
    P = np.column_stack([np.tile(Xs.ravel(), zs.size), np.tile(Y.ravel(), zs.size),
                         np.repeat(org[2] + sp[2] * zs, Xs.size)])
    s = loc.sample(np.asarray(start, float), P)
    U = np.nan_to_num(np.stack([s["ux"], s["uy"], s["uz"]], axis=-1)).reshape(zs.size, rows.size, ny, 3)
    U = interp1d(rows, U, axis=1, assume_sorted=True)(np.arange(nx))          # (planes, nx, ny, 3)
    # the moving envelope on the planes each plane's warped points reach (a few planes in memory, not a volume)
    reach = zs[:, None] + np.stack([U[..., 2].min(axis=(1, 2)), U[..., 2].max(axis=(1, 2))], axis=1) / sp[2]
    cache = {}

    def mov_env(k):
        if k not in cache:
            cache[k] = envelope(mov[:, :, k])
        return cache[k]

    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    planes = []
    for n, z in enumerate(zs):
        u = U[n]
        lo, hi = (int(np.clip(v, 0, nz - 1)) for v in (np.floor(reach[n, 0]), np.ceil(reach[n, 1])))
        sub = np.stack([mov_env(k) for k in range(lo, hi + 1)], axis=2)
        for k in [k for k in cache if k < lo]:      # planes left behind (zs ascends)
            del cache[k]
        warped = ndimage.map_coordinates(sub, [ii + u[..., 0] / sp[0], jj + u[..., 1] / sp[1],
                                               z - lo + u[..., 2] / sp[2]], order=1, mode="constant")
        bm = block_match(envelope(ref[:, :, z]), warped, sp[:2], org[:2], window=tuple(settings.window),
                         overlap=(0.5, 0.5), search=tuple(settings.search), median_size=3, subsample=True,
                         compand_strain=None)
        planes.append(bm)
    # the planes' windows side by side: one row of windows per depth, as in a frame
    found = BlockMatchResult(planes[0].x, np.concatenate([p.y for p in planes]),
                             *(np.concatenate([getattr(p, k) for p in planes], axis=1)
                               for k in ("raw", "displacement", "ncc")))
    m3 = np.broadcast_to(np.asarray(DEFAULT_MARGIN_3D if margin is None else margin, float), (3,))
    cut = unmatched_crop(found, (nx, ny), sp[:2], org[:2], margin=m3[:2])
    if cut is None:
        return None
    b = int(cut.region.rows[1])
    region = EchoBox(((0, b), (0, ny), (0, nz)), (nx, ny, nz), tuple(float(v) for v in sp),
                     tuple(float(v) for v in org), cut.region.excluded)
    return VolumeCrop(region, _margin_pixels(m3, sp), False, time.perf_counter() - t)
