"""Volumes of mechanically swept 3D probes (:class:`femreg.probes.Swept`): scan-converted to a Cartesian voxel grid,
registered there as any volume (:func:`femreg.volume.register_volume`), the result read at the samples' physical
positions (:class:`femreg.volume_result.SweptResult`).

Scan conversion (:func:`scan_convert`): the RF of each volume is interpolated with the tricubic B-spline of its
samples in the sample indices (:class:`femreg.voxels.SplineVolume`, the interpolant the registration itself warps
with) at the voxel centres of the Cartesian box inscribed in the fan (:func:`inscribed_box`: every voxel at least
one sample in from the first and two from the last sample of every axis, the spline's support).  Voxels: the range
step axially; laterally the line pitch of a linear array (its lines keep their y under the tilt, so the grid hits
them and nothing is interpolated across lines), the line spacing at the box's middle depth of a curved one;
elevationally the frame spacing at the box's middle depth; both at most a quarter of the RF phase's period along
that axis (:func:`grid_spacing_for`; ``grid_spacing`` overrides the last two).  The fan
outside the box (the corners near the face and at the bottom) is not registered: ``result.excluded`` says how much.
"""
from __future__ import annotations

import time

import numpy as np

from .errors import InputError
from .probes import Swept, as_geometry
from .speckle import rf_period
from .volume_result import SweptResult
from .voxels import SplineVolume, validate_volume

__all__ = ["swept_spacing", "inscribed_box", "grid_spacing_for", "cartesian_grid", "scan_convert",
           "register_swept", "scan_convert_sequence", "SweptConversion", "VOXELS_PER_PHASE_PERIOD"]

#: Voxels interpolated per block of :func:`scan_convert` (bounds its temporaries to ~100 MB).
SCAN_CHUNK = 1 << 21


def swept_spacing(spacing, geometry: Swept, origin):
    """Validate ``spacing`` = (dr mm, line pitch: mm for a linear array / deg equal to a curved array's pitch,
    frame step deg equal to the geometry's) and ``origin`` = (r_0 mm, first line y mm for a linear array / 0,
    0); return them as float arrays (3,)."""
    sp = np.atleast_1d(np.asarray(spacing, float)).ravel()
    what = "mm" if geometry.array is None else "deg"
    if sp.size != 3 or not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise InputError(f"with a swept geometry, spacing is (dr mm, line pitch {what}, frame step deg), three "
                         f"positive numbers; got {spacing!r}")
    if geometry.array is not None and not np.isclose(sp[1], geometry.array.angle_pitch_deg, rtol=1e-6):
        raise InputError(f"spacing[1] = {sp[1]:g} deg differs from the array's angle pitch "
                         f"{geometry.array.angle_pitch_deg:g} deg")
    if not np.isclose(sp[2], geometry.angle_step_deg, rtol=1e-6):
        raise InputError(f"spacing[2] = {sp[2]:g} deg differs from the swept geometry's angle step "
                         f"{geometry.angle_step_deg:g} deg")
    org = np.asarray(origin, float).ravel()
    if org.size != 3 or not np.all(np.isfinite(org)) or org[2] != 0 or (geometry.array is not None and org[1] != 0):
        raise InputError(f"with a swept geometry, origin is (range of the first sample mm, "
                         f"{'y of the first line mm' if geometry.array is None else '0'}, 0): frames (and a curved "
                         f"array's rays) are centred on angle 0; got {origin!r}")
    if geometry.sweep_radius_mm + org[0] <= 0 or (geometry.array is not None
                                                    and geometry.array.radius_mm + org[0] <= 0):
        raise InputError(f"the first sample (range {org[0]:g} mm) lies at or behind an apex or the sweep axis")
    return sp, org


def _valid(geometry, points, shape, spacing, origin):
    """(n,) bool: points whose sample indices are at least 1 from the first and 2 from the last on every axis."""
    idx = geometry.physical_to_index(points, shape, spacing, origin)
    hi = np.asarray(shape, float)[:, None] - 2.0
    return np.all((idx >= 1.0) & (idx <= hi), axis=0)


def inscribed_box(geometry: Swept, shape, spacing, origin, n: int = 48):
    """``(lo, hi)`` (3,) mm: an axis-aligned box inside the fan of a swept volume (every point at least one sample
    in from the first and two from the last sample of every axis).  Found on an ``n**3`` lattice over the fan's
    bounding box by peeling, one face at a time, the face with the largest fraction of points outside, until
    none is left (a convex region: the box is the largest such lattice box up to one lattice step); then each
    face pushed out by bisection to the fan's edge."""
    X, Y, Z = geometry.sample_positions(shape, spacing, origin)
    lo0 = np.array([X.min(), Y.min(), Z.min()])
    hi0 = np.array([X.max(), Y.max(), Z.max()])
    axes = [np.linspace(lo0[a], hi0[a], n) for a in range(3)]
    G = np.meshgrid(*axes, indexing="ij")
    ok = _valid(geometry, np.column_stack([g.ravel() for g in G]), shape, spacing, origin).reshape(n, n, n)
    if not ok.any():
        raise InputError("no part of the swept volume is at least one sample in from its edges")
    b = [0, n - 1, 0, n - 1, 0, n - 1]
    while True:
        sub = ok[b[0]:b[1] + 1, b[2]:b[3] + 1, b[4]:b[5] + 1]
        if sub.all():
            break
        best, face = -1.0, None
        for a in range(3):
            if b[2 * a + 1] - b[2 * a] < 1:
                continue
            for side in (0, 1):
                sl = [slice(None)] * 3
                sl[a] = 0 if side == 0 else -1
                frac = 1.0 - float(np.mean(sub[tuple(sl)]))
                if frac > best:
                    best, face = frac, (a, side)
        if face is None:
            raise InputError("no box of the swept volume lies inside its fan")
        a, side = face
        b[2 * a + side] += 1 if side == 0 else -1
    lo = np.array([axes[a][b[2 * a]] for a in range(3)])
    hi = np.array([axes[a][b[2 * a + 1]] for a in range(3)])

    def inside(lo_, hi_):   # the box's faces sampled on a 48 x 48 lattice each
        t = np.linspace(0.0, 1.0, 48)
        pts = []
        for a in range(3):
            o = [q for q in range(3) if q != a]
            U, V = np.meshgrid(lo_[o[0]] + t * (hi_[o[0]] - lo_[o[0]]), lo_[o[1]] + t * (hi_[o[1]] - lo_[o[1]]),
                               indexing="ij")
            for c in (lo_[a], hi_[a]):
                P = np.empty((U.size, 3))
                P[:, a], P[:, o[0]], P[:, o[1]] = c, U.ravel(), V.ravel()
                pts.append(P)
        return bool(np.all(_valid(geometry, np.vstack(pts), shape, spacing, origin)))

    for a in range(3):      # push each face out towards the next lattice plane while the box stays inside
        step = (hi0[a] - lo0[a]) / (n - 1)
        for side in (0, 1):
            ok_at, bad_at = 0.0, step
            for _ in range(12):
                mid = 0.5 * (ok_at + bad_at)
                l2, h2 = lo.copy(), hi.copy()
                if side == 0:
                    l2[a] -= mid
                else:
                    h2[a] += mid
                if inside(l2, h2):
                    ok_at = mid
                else:
                    bad_at = mid
            if side == 0:
                lo[a] -= ok_at
            else:
                hi[a] += ok_at
    return lo, hi


#: Voxels per period of the RF's phase along a Cartesian axis the rays are tilted towards (:func:`grid_spacing_for`).
VOXELS_PER_PHASE_PERIOD = 4.0


def grid_spacing_for(geometry: Swept, spacing, lo, hi, period: float) -> np.ndarray:
    """Voxel spacing (3,) mm of the scan-converted grid: the range step axially; laterally the line pitch of a
    linear array, else the line spacing at the box's middle depth; elevationally the frame spacing there; each
    of the last two at most ``period / (4 sin t)``, ``t`` the largest ray angle (frame tilt) in the box and
    ``period`` the axial RF period mm.  Why: the RF's phase runs along the ray, so along z it turns once per
    ``period / sin(phi)``; a grid coarser than that aliases the carrier (measured, docs/geometry.md: an
    elevational stretch of 0.5 % read as -0.27 % on 0.5 mm planes at +-12 deg, 0.50 % on 0.13 mm)."""
    corners = np.array([[lo[0] if i == 0 else hi[0], lo[1] if j == 0 else hi[1], lo[2] if k == 0 else hi[2]]
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    _, line, phi = geometry.to_beam(corners[:, 0], corners[:, 1], corners[:, 2])
    a_mid = 0.5 * (lo[0] + hi[0])

    def cap(h, angle):
        s = np.sin(float(np.max(np.abs(angle))))
        return min(h, period / (VOXELS_PER_PHASE_PERIOD * s)) if s > 0 else h

    lat = spacing[1] if geometry.array is None else \
        cap((geometry.array.radius_mm + a_mid) * geometry.array.pitch_rad, line)
    return np.array([spacing[0], lat, cap((geometry.sweep_radius_mm + a_mid) * geometry.step_rad, phi)])


def cartesian_grid(geometry, volume, spacing, origin, grid_spacing=None):
    """``(n (3,), spacing (3,), origin (3,))`` of the Cartesian voxel grid inside the fan of ``volume`` (module
    docstring; ``spacing``, ``origin`` validated by :func:`swept_spacing`): the ``grid`` of :func:`scan_convert`,
    one grid for every volume of a sequence."""
    geometry = as_geometry(geometry)
    if not isinstance(geometry, Swept):
        raise InputError(f"a swept volume's grid needs a femreg.Swept geometry, got {geometry!r}")
    spacing, origin = swept_spacing(spacing, geometry, origin)
    volume = np.asarray(volume)
    shape = volume.shape
    lo, hi = inscribed_box(geometry, shape, spacing, origin)
    nx = shape[0]
    period = rf_period(volume[:, ::4, ::4].reshape(nx, -1), spacing)
    h = grid_spacing_for(geometry, spacing, lo, hi, period)
    if grid_spacing is not None:
        g = np.atleast_1d(np.asarray(grid_spacing, float)).ravel()
        if g.size != 2 or not np.all(np.isfinite(g)) or np.any(g <= 0):
            raise InputError(f"grid_spacing is (lateral mm, elevational mm), got {grid_spacing!r}")
        h[1:] = g
    n = np.floor((hi - lo) / h + 1e-9).astype(int) + 1
    org = lo + 0.5 * ((hi - lo) - (n - 1) * h)           # centred in the box
    if geometry.array is None and grid_spacing is None:
        # on the lines y_j = y_0 + j dy: exact in y, nothing interpolated across lines
        j0 = int(np.ceil((lo[1] - origin[1]) / spacing[1] - 1e-9))
        j1 = int(np.floor((hi[1] - origin[1]) / spacing[1] + 1e-9))
        n[1], org[1] = j1 - j0 + 1, origin[1] + j0 * spacing[1]
    if np.any(n < 4):
        raise InputError(f"the Cartesian box inside the swept fan has {tuple(int(v) for v in n)} voxels; a volume "
                         "needs at least 4 per axis (more frames or lines, or a finer grid_spacing)")
    return n, h, org


def scan_convert(volume, geometry, spacing, origin=(0.0, 0.0, 0.0), *, grid_spacing=None, grid=None):
    """A swept volume (n_samples, n_lines, n_frames) -> ``(voxels, spacing (3,) mm, origin (3,) mm)`` on the
    Cartesian grid inside its fan (module docstring); ``grid`` = ``(shape, spacing, origin)`` of a grid to use
    instead (a pair is converted onto one grid)."""
    geometry = as_geometry(geometry)
    if not isinstance(geometry, Swept):
        raise InputError(f"scan_convert needs a femreg.Swept geometry, got {geometry!r}")
    vol = validate_volume(volume, "swept volume")
    sp, org = swept_spacing(spacing, geometry, origin)
    n, h, o = grid if grid is not None else cartesian_grid(geometry, vol, sp, org, grid_spacing)
    n = tuple(int(v) for v in n)
    spline = SplineVolume(vol, (1.0, 1.0, 1.0), keep_data=False)
    del vol
    out = np.empty(n)
    flat = out.reshape(-1)
    axes = [o[a] + h[a] * np.arange(n[a]) for a in range(3)]
    per_x = n[1] * n[2]
    step = max(1, SCAN_CHUNK // per_x)
    for i0 in range(0, n[0], step):
        G = np.meshgrid(axes[0][i0:i0 + step], axes[1], axes[2], indexing="ij")
        idx = geometry.physical_to_index(np.column_stack([g.ravel() for g in G]), spacing=sp, origin=org,
                                         shape=spline.shape)
        flat[i0 * per_x:i0 * per_x + idx.shape[1]] = spline.at_index(idx)
    return out, np.asarray(h, float), np.asarray(o, float)


def register_swept(reference_image, moving_image, *, geometry, spacing, origin=(0.0, 0.0, 0.0), register,
                   grid_spacing=None, **kw) -> SweptResult:
    """``femreg.register`` for a swept probe's volumes: both scan-converted onto one Cartesian grid inside the fan
    (:func:`scan_convert`), registered by ``register`` (:func:`femreg.volume.register_volume`) with ``kw``, the
    result a :class:`~femreg.volume_result.SweptResult` (physical Cartesian mesh and fields; ``on_grid`` at the
    samples).  ``grid_spacing``: (lateral, elevational) voxel spacing mm of the Cartesian grid."""
    geometry = as_geometry(geometry)
    for bad in ("mesh", "offset"):
        if kw.get(bad) is not None:
            raise InputError(f"{bad}= is not supported with a swept geometry (the mesh is built on the "
                             "scan-converted grid)")
    ref = validate_volume(reference_image, "reference volume")
    mov = validate_volume(moving_image, "moving volume")
    if ref.shape != mov.shape:
        raise InputError(f"volume shape mismatch: reference {ref.shape} vs moving {mov.shape}")
    sp, org = swept_spacing(spacing, geometry, origin)
    shape = ref.shape
    t = time.perf_counter()
    grid = cartesian_grid(geometry, ref, sp, org, grid_spacing)
    A, h, o = scan_convert(ref, geometry, sp, org, grid=grid)
    del ref
    B = scan_convert(mov, geometry, sp, org, grid=grid)[0]
    del mov
    t_scan = time.perf_counter() - t
    res = register(A, B, spacing=h, origin=o, **kw)
    out = SweptConversion(geometry, shape, sp, org, (A.shape, h, o)).result(res)
    out.timings = dict(res.timings, scan_convert=t_scan, total=res.timings.get("total", 0.0) + t_scan)
    return out


class SweptConversion:
    """How the volumes of a swept probe were scan-converted (``geometry``, the sample grid ``shape``, ``spacing``,
    ``origin``, and ``cartesian`` = (shape, spacing, origin) of the common Cartesian grid), and how a result
    registered on that grid becomes a :class:`~femreg.volume_result.SweptResult` (:meth:`result`)."""

    def __init__(self, geometry, shape, spacing, origin, cartesian):
        self.geometry = geometry
        self.shape = tuple(int(v) for v in shape)
        self.spacing, self.origin = np.asarray(spacing, float), np.asarray(origin, float)
        self.cartesian = (tuple(int(v) for v in cartesian[0]), np.asarray(cartesian[1], float),
                          np.asarray(cartesian[2], float))
        n, h, o = self.cartesian
        lo, hi = o, o + (np.array(n) - 1) * h
        P = np.column_stack([c.ravel() for c in geometry.sample_positions(self.shape, self.spacing, self.origin)])
        outside = float(np.mean(np.any((P < lo - 1e-9) | (P > hi + 1e-9), axis=1)))
        box = ", ".join(f"{a} {lo[k]:.1f}..{hi[k]:.1f}" for k, a in enumerate("xyz"))
        #: what of the fan is not registered (the result's ``excluded`` starts with it)
        self.note = f"the fan outside the Cartesian box inside it ({box} mm; {100 * outside:.0f} % of the samples)"

    def result(self, res) -> SweptResult:
        """``res`` (a :class:`~femreg.volume_result.VolumeResult` on the Cartesian grid, already a
        :class:`~femreg.volume_result.SweptResult`: returned as it is) as the result of the swept volumes."""
        if isinstance(res, SweptResult):
            return res
        out = SweptResult.of(res, geometry=self.geometry, shape=self.shape, spacing=self.spacing,
                             origin=self.origin, cartesian=self.cartesian)
        out.excluded = self.note if not res.excluded else f"{self.note}; {res.excluded}"
        for k in ("auto_alpha", "refinement"):
            if hasattr(res, k):
                setattr(out, k, getattr(res, k))
        return out

    def params(self) -> dict:
        """The conversion as JSON-able values (recorded with a tracking run, so a resume must match it)."""
        n, h, o = self.cartesian
        return {"geometry": self.geometry.to_dict(), "sample_shape": list(self.shape),
                "sample_spacing": [float(v) for v in self.spacing], "sample_origin": [float(v) for v in self.origin],
                "cartesian_shape": list(n), "cartesian_spacing": [float(v) for v in h],
                "cartesian_origin": [float(v) for v in o]}


def scan_convert_sequence(volumes, geometry, spacing, origin=(0.0, 0.0, 0.0), *, grid_spacing=None):
    """A sequence of swept volumes (each (n_samples, n_lines, n_frames), one shape) -> ``(voxels, conversion)``:
    every volume scan-converted once (:func:`scan_convert`) onto ONE Cartesian grid, the grid of volume 0
    (:func:`cartesian_grid`), ``voxels`` a list of (n_x, n_y, n_z) arrays on it, ``conversion`` the
    :class:`SweptConversion` (grid spacing and origin in ``conversion.cartesian``).  What
    :func:`femreg.volume.track_volume` tracks for ``geometry=femreg.Swept(...)``."""
    geometry = as_geometry(geometry)
    if not isinstance(geometry, Swept):
        raise InputError(f"a swept volume sequence needs a femreg.Swept geometry, got {geometry!r}")
    vols = [validate_volume(v, f"volume {k}") for k, v in enumerate(volumes)]
    shapes = {v.shape for v in vols}
    if len(shapes) != 1:
        raise InputError(f"every volume of a swept sequence must have one shape, got {sorted(shapes)}")
    sp, org = swept_spacing(spacing, geometry, origin)
    grid = cartesian_grid(geometry, vols[0], sp, org, grid_spacing)
    out, h, o = [], None, None
    for k in range(len(vols)):
        A, h, o = scan_convert(vols[k], geometry, sp, org, grid=grid)
        vols[k] = None          # the samples are not needed once converted
        out.append(A)
    return out, SweptConversion(geometry, shapes.pop(), sp, org, (out[0].shape, h, o))

