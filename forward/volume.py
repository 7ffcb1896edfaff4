r"""RF volumes of a matrix or mechanically swept probe: separable 3D PSF with depth focus, point scatterers in a
volume, noise, warps by any 3D displacement field, and the paper's 3D phantom imaged as volumes.

Coordinates (mm): ``x`` = depth (axial, the beam direction), ``y`` = lateral, ``z`` = elevational.  Volumes are
arrays ``(n_axial, n_lateral, n_elevational)``; voxel ``[i, j, k]`` has its centre at
``origin + (i dx, j dy, k dz)`` (:class:`ImagingVolume`).

PSF (:class:`PSF3D`)
--------------------
Separable, for a scatterer at ``(x_s, y_s, z_s)`` seen at voxel ``(x, y, z)``:

.. math::

    h = h_{ax}(x - x_s)\, \frac{\sigma_y^0}{\sigma_y(x_s)} e^{-\frac{(y - y_s)^2}{2\sigma_y(x_s)^2}}
        \, \frac{\sigma_z^0}{\sigma_z(x)} e^{-\frac{(z - z_s)^2}{2\sigma_z(x)^2}},

``h_ax`` the Gaussian-modulated pulse of :class:`forward.ultrasound.PSF` (same pulse-length and FWHM conventions),
``sigma^0`` the pulse-echo beam width at its focus (``FWHM / (2 sqrt(2 ln 2))`` of the amplitude) and
``sigma(d) = sigma^0 sqrt(1 + ((d - d_f) / z_R)^2)`` the Gaussian-beam widening away from the focus depth
``d_f``, with Rayleigh range ``z_R = pi w_0^2 / lambda``, ``w_0 = 2 sigma^0`` the one-way waist (a one-way
amplitude ``exp(-r^2 / w^2)`` squared is the pulse-echo ``exp(-r^2 / (2 sigma^2))``).  The factor
``sigma^0 / sigma`` keeps the energy of the beam cross-section.  A focus of ``None`` is a beam focused at every
depth (dynamic receive focusing): spatially invariant, as the paper's 2D PSF.  A matrix array or a swept probe's
elevational lens has a fixed elevational focus and a 1-3 mm elevational beam.

Rendering (:func:`render_volume`)
---------------------------------
Exact in depth and lateral position for every scatterer (sparse products as :func:`forward.ultrasound.render_rf`);
in elevation every scatterer is split linearly between the two nearest of a set of fine sub-planes
(``spacing <= sigma_z / 8``: the linear interpolation keeps the elevational centroid exact and changes the
Gaussian by less than 0.2 % of its peak), each sub-plane's RF image is one sparse product, and the elevational
beam is applied as one dense matrix product per depth band.  Cost about ``N K_x 2 K_y + n_x n_y n_sub n_z``
(``K`` taps per scatterer), against ``N K_x K_y K_z`` for a direct sum.

Public API: :class:`PSF3D`, :class:`VolumeProbe`, :data:`VOLUME_PROBES`, :class:`ImagingVolume`,
:func:`make_scatterers_3d`, :func:`render_volume`, :class:`Affine3D`, :class:`FEVolumeField`,
:class:`FunctionField3D`, :func:`make_volume_pair` -> :class:`VolumePair`, :func:`make_volume_sequence` ->
:class:`VolumeSequence`, :func:`paper_volume_sequence` (cached), :func:`central_plane`.
"""
from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import asdict, dataclass, field as dc_field
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .pairs import _echo_gain as _depth_gain  # one home for the depth gains of frames and volumes (grid.x: depth)
from .ultrasound import PSF, SPEED_OF_SOUND_MM_PER_S, noise_sigma, positive

__all__ = ["PSF3D", "VolumeProbe", "VOLUME_PROBES", "as_volume_probe", "ImagingVolume", "Scatterers3D",
           "make_scatterers_3d", "render_volume", "Affine3D", "FEVolumeField", "FunctionField3D", "VolumePair",
           "VolumeSequence", "make_volume_pair", "make_volume_sequence", "paper_volume_sequence",
           "load_volume_sequence", "central_plane", "ScaledField", "STRAIN_COMPONENTS_3D", "SCATTERERS_PER_CELL_3D"]

_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
#: Order of the six strain components everywhere in 3D (tensor shear, not engineering).
STRAIN_COMPONENTS_3D = ("exx", "eyy", "ezz", "exy", "exz", "eyz")
#: Scatterers per ``sigma_x sigma_y sigma_z`` of the PSF: 13 per -6 dB resolution volume, fully developed speckle
#: (envelope mean/std within 2 % of the Rayleigh 1.91, measured in the tests).
SCATTERERS_PER_CELL_3D = 1.0
#: Bump when anything changes the rendered frames of :func:`paper_volume_sequence` (invalidates its cache).
VOLUME_FORMAT_VERSION = 2


def _focus(value, name):
    if value is None:
        return None
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be a finite depth in mm or None, got {value!r}")
    return v


@dataclass(frozen=True)
class PSF3D:
    """Separable RF point spread function of a volume (module docstring).

    Parameters
    ----------
    center_frequency_hz, pulse_length_s : float
        Carrier f0 (Hz) and -6 dB duration of the pulse envelope in echo time (s), as :class:`PSF`.
    lateral_fwhm_mm, elevational_fwhm_mm : float
        Pulse-echo amplitude FWHM of the beam at its focus, mm (elevational 1-3 mm for a matrix / swept probe).
    lateral_focus_mm, elevational_focus_mm : float or None
        Focus depths, mm; None: focused at every depth (no widening).
    speed_of_sound_mm_per_s : float
    truncation : float
        Support of each factor in standard deviations (each side).
    """

    center_frequency_hz: float = 7.0e6
    pulse_length_s: float = 2.365 / 7.0e6
    lateral_fwhm_mm: float = 0.9
    elevational_fwhm_mm: float = 2.0
    lateral_focus_mm: float | None = None
    elevational_focus_mm: float | None = 20.0
    speed_of_sound_mm_per_s: float = SPEED_OF_SOUND_MM_PER_S
    truncation: float = 4.0

    def __post_init__(self):
        for name in ("center_frequency_hz", "pulse_length_s", "lateral_fwhm_mm", "elevational_fwhm_mm",
                     "speed_of_sound_mm_per_s", "truncation"):
            object.__setattr__(self, name, positive(name, getattr(self, name)))
        for name in ("lateral_focus_mm", "elevational_focus_mm"):
            object.__setattr__(self, name, _focus(getattr(self, name), name))

    @property
    def pulse(self) -> PSF:
        """The axial pulse (and the lateral profile at focus) as the 2D :class:`PSF`."""
        return PSF(self.center_frequency_hz, self.pulse_length_s, self.lateral_fwhm_mm,
                   self.speed_of_sound_mm_per_s, self.truncation)

    @property
    def sigma_axial_mm(self) -> float:
        return self.pulse.sigma_axial_mm

    @property
    def wavelength_mm(self) -> float:
        return self.speed_of_sound_mm_per_s / self.center_frequency_hz

    def _sigma(self, fwhm, focus, depth_mm):
        s0 = fwhm / _FWHM_PER_SIGMA
        d = np.asarray(depth_mm, dtype=float)
        if focus is None:
            return np.full(d.shape, s0)
        z_r = math.pi * (2.0 * s0) ** 2 / self.wavelength_mm
        return s0 * np.sqrt(1.0 + ((d - focus) / z_r) ** 2)

    def sigma_lateral_mm(self, depth_mm=None):
        """Lateral standard deviation at ``depth_mm`` (at the focus if None), mm."""
        return self._sigma(self.lateral_fwhm_mm, self.lateral_focus_mm,
                           (self.lateral_focus_mm or 0.0) if depth_mm is None else depth_mm)

    def sigma_elevational_mm(self, depth_mm=None):
        """Elevational standard deviation at ``depth_mm`` (at the focus if None), mm."""
        return self._sigma(self.elevational_fwhm_mm, self.elevational_focus_mm,
                           (self.elevational_focus_mm or 0.0) if depth_mm is None else depth_mm)

    def axial(self, d_mm):
        """Axial pulse ``h_ax`` at depth offsets ``d_mm``, peak 1 at 0."""
        return self.pulse.axial(d_mm)

    def lateral(self, d_mm, depth_mm):
        """Lateral beam factor (with its energy-keeping amplitude) at offsets ``d_mm`` and depths ``depth_mm``."""
        s = self.sigma_lateral_mm(depth_mm)
        return (self.lateral_fwhm_mm / _FWHM_PER_SIGMA / s) * np.exp(-0.5 * (np.asarray(d_mm, float) / s) ** 2)

    def elevational(self, d_mm, depth_mm):
        """Elevational beam factor at offsets ``d_mm`` and depths ``depth_mm``."""
        s = self.sigma_elevational_mm(depth_mm)
        return (self.elevational_fwhm_mm / _FWHM_PER_SIGMA / s) * np.exp(-0.5 * (np.asarray(d_mm, float) / s) ** 2)

    def half_support_mm(self, depth_max_mm: float = 0.0) -> tuple[float, float, float]:
        """(axial, lateral, elevational) half-width of the truncated support down to ``depth_max_mm``, mm."""
        t = self.truncation
        dmax = float(depth_max_mm)
        sy = max(float(self.sigma_lateral_mm(0.0)), float(self.sigma_lateral_mm(dmax)), float(self.sigma_lateral_mm()))
        sz = max(float(self.sigma_elevational_mm(0.0)), float(self.sigma_elevational_mm(dmax)),
                 float(self.sigma_elevational_mm()))
        return t * self.sigma_axial_mm, t * sy, t * sz

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class VolumeProbe:
    """A matrix-array (or mechanically swept) probe and its volume sampling.

    ``f0_mhz`` centre frequency, ``fs_mhz`` axial sampling (axial voxel ``c / (2 fs)``), ``pitch_mm`` lateral and
    ``elevation_pitch_mm`` elevational line spacing, ``beam_fwhm_mm`` / ``elevation_fwhm_mm`` pulse-echo beam
    widths at focus, ``cycles`` the -6 dB pulse duration in carrier cycles, ``lateral_focus_mm`` (None: dynamic
    receive focus) and ``elevation_focus_mm`` (the elevational lens).
    """

    f0_mhz: float = 7.0
    fs_mhz: float = 30.8
    pitch_mm: float = 0.2
    elevation_pitch_mm: float = 0.25
    beam_fwhm_mm: float = 0.9
    elevation_fwhm_mm: float = 2.0
    cycles: float = 2.365
    lateral_focus_mm: float | None = None
    elevation_focus_mm: float | None = 20.0
    name: str = "matrix7"
    c_m_s: float = 1540.0

    def __post_init__(self):
        for k in ("f0_mhz", "fs_mhz", "pitch_mm", "elevation_pitch_mm", "beam_fwhm_mm", "elevation_fwhm_mm",
                  "cycles", "c_m_s"):
            object.__setattr__(self, k, positive(f"probe {k}", getattr(self, k)))
        if self.fs_mhz <= 2.0 * self.f0_mhz:
            raise ValueError(f"probe sampling fs = {self.fs_mhz:g} MHz must exceed twice the centre frequency "
                             f"f0 = {self.f0_mhz:g} MHz")

    @property
    def spacing(self) -> tuple[float, float, float]:
        """(axial, lateral, elevational) voxel spacing, mm."""
        return (self.c_m_s * 1e3 / (2.0 * self.fs_mhz * 1e6), self.pitch_mm, self.elevation_pitch_mm)

    def psf(self) -> PSF3D:
        return PSF3D(self.f0_mhz * 1e6, self.cycles / (self.f0_mhz * 1e6), self.beam_fwhm_mm,
                     self.elevation_fwhm_mm, self.lateral_focus_mm, self.elevation_focus_mm, self.c_m_s * 1e3)

    def density_per_mm3(self, scatterers_per_cell: float = SCATTERERS_PER_CELL_3D) -> float:
        """Scatterers per mm^3 giving ``scatterers_per_cell`` per ``sigma_x sigma_y sigma_z`` at focus."""
        p = self.psf()
        return float(scatterers_per_cell) / (p.sigma_axial_mm * float(p.sigma_lateral_mm())
                                             * float(p.sigma_elevational_mm()))

    def to_dict(self) -> dict:
        return asdict(self)


#: Presets: a 7 MHz matrix array sampled as ~800 x 100 x 60 voxels per 20 x 20 x 15 mm; the paper's 5.5 MHz PSF
#: and 40 MHz / 0.3 mm sampling with a 2 mm elevational beam on 0.5 mm slices; a 3.5 MHz abdominal swept probe;
#: a 12 MHz high-frequency matrix array.
VOLUME_PROBES = {
    "matrix7": VolumeProbe(),
    "paper3d": VolumeProbe(5.5, 40.0, 0.3, 0.5, 1.4, 2.0, 2.365, None, 30.0, name="paper3d"),
    "swept3": VolumeProbe(3.5, 20.0, 0.4, 0.5, 2.2, 3.0, 2.365, None, 40.0, name="swept3"),
    "matrix12": VolumeProbe(12.0, 50.0, 0.1, 0.2, 0.5, 1.2, 2.365, None, 15.0, name="matrix12"),
}


def as_volume_probe(spec) -> VolumeProbe:
    """A :class:`VolumeProbe` from a preset name, a VolumeProbe or a dict of its parameters."""
    if isinstance(spec, VolumeProbe):
        return spec
    if isinstance(spec, str):
        if spec not in VOLUME_PROBES:
            raise ValueError(f"unknown volume probe preset {spec!r}: expected one of {tuple(VOLUME_PROBES)}")
        return VOLUME_PROBES[spec]
    if isinstance(spec, dict):
        return VolumeProbe(**spec)
    raise ValueError(f"probe must be a preset name, a VolumeProbe or a dict, got {type(spec).__name__}")


@dataclass(frozen=True)
class ImagingVolume:
    """Regular voxel grid: ``shape`` (n_axial, n_lateral, n_elevational), ``spacing`` (dx, dy, dz) mm and
    ``origin`` (x0, y0, z0) mm, the centre of voxel ``[0, 0, 0]``."""

    shape: tuple
    spacing: tuple
    origin: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        try:
            shape = tuple(int(v) for v in self.shape)
            spacing = tuple(float(v) for v in self.spacing)
            origin = tuple(float(v) for v in self.origin)
        except (TypeError, ValueError):
            raise ValueError(f"ImagingVolume needs 3 integers shape, 3 spacings and 3 origin values, got "
                             f"{self.shape!r}, {self.spacing!r}, {self.origin!r}") from None
        if len(shape) != 3 or len(spacing) != 3 or len(origin) != 3:
            raise ValueError(f"ImagingVolume shape, spacing and origin need 3 values each, got {shape}, "
                             f"{spacing}, {origin}")
        if min(shape) < 1 or any(int(a) != b for a, b in zip(self.shape, shape)):
            raise ValueError(f"shape must be positive integers, got {self.shape!r}")
        for name, v in zip(("dx", "dy", "dz"), spacing):
            positive(f"spacing {name} (mm)", v)
        if not all(math.isfinite(o) for o in origin):
            raise ValueError(f"origin must be finite, got {origin!r}")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "spacing", spacing)
        object.__setattr__(self, "origin", origin)

    @classmethod
    def centred(cls, size_mm=(20.0, 20.0, 15.0), spacing=(0.025, 0.2, 0.25), top_mm: float = 0.0,
                ) -> "ImagingVolume":
        """``size_mm`` = (depth, width, elevation) from ``top_mm`` down, centred on y = 0 and z = 0."""
        try:
            d, w, e = (positive("size_mm", s) for s in size_mm)
            dx, dy, dz = (positive("spacing", s) for s in spacing)
        except TypeError:
            raise ValueError(f"size_mm and spacing need 3 values each, got {size_mm!r}, {spacing!r}") from None
        n = (max(1, int(round(d / dx))), max(1, int(round(w / dy))), max(1, int(round(e / dz))))
        return cls(n, (dx, dy, dz), (float(top_mm), -0.5 * (n[1] - 1) * dy, -0.5 * (n[2] - 1) * dz))

    def axis(self, a: int) -> np.ndarray:
        """Voxel-centre coordinates along axis ``a`` (0 axial, 1 lateral, 2 elevational), mm."""
        return self.origin[a] + self.spacing[a] * np.arange(self.shape[a])

    @property
    def x(self):
        return self.axis(0)

    @property
    def y(self):
        return self.axis(1)

    @property
    def z(self):
        return self.axis(2)

    def points(self) -> np.ndarray:
        """All voxel centres, (n, 3) [x, y, z] mm, C order of the volume."""
        X, Y, Z = np.meshgrid(self.x, self.y, self.z, indexing="ij")
        return np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])

    def extent(self) -> tuple:
        """Voxel-edge bounding box ``(x_min, x_max, y_min, y_max, z_min, z_max)``, mm."""
        out = []
        for a in range(3):
            h = 0.5 * self.spacing[a]
            out += [self.origin[a] - h, self.origin[a] + (self.shape[a] - 1) * self.spacing[a] + h]
        return tuple(out)

    def to_dict(self) -> dict:
        return dict(shape=list(self.shape), spacing=list(self.spacing), origin=list(self.origin))


@dataclass
class Scatterers3D:
    """Point scatterers: ``positions`` (n, 3) [x, y, z] mm and ``amplitudes`` (n,)."""

    positions: np.ndarray
    amplitudes: np.ndarray

    def __len__(self) -> int:
        return len(self.amplitudes)


def make_scatterers_3d(rng: np.random.Generator, box, *, density_per_mm3: float,
                       cell_aspect=(1.0, 1.0, 1.0)) -> Scatterers3D:
    """Stratified uniform scatterers (one per cell, uniformly inside it) with standard normal amplitudes.

    ``box`` = (x_min, x_max, y_min, y_max, z_min, z_max) mm; the cells have volume ``1 / density_per_mm3`` and edge
    ratios ``cell_aspect`` (the PSF's sigma ratios give as many cells per resolution cell along each axis), as the
    2D :func:`forward.ultrasound.make_scatterers` (``placement="stratified"``).
    """
    dens = positive("density_per_mm3", density_per_mm3)
    b = [float(v) for v in box]
    L = np.array([b[1] - b[0], b[3] - b[2], b[5] - b[4]])
    if not np.all(L > 0):
        raise ValueError(f"scatterer box must have max > min on every axis, got {box!r}")
    asp = np.array([positive("cell_aspect", a) for a in cell_aspect])
    cell = asp * (1.0 / (dens * np.prod(asp))) ** (1.0 / 3.0)     # edges with product 1/density
    n = np.maximum(1, np.round(L / cell).astype(int))
    total = int(np.prod(n))
    if total > 60_000_000:
        raise ValueError(f"{total} scatterers requested (box {L.round(1).tolist()} mm at {dens:g} per mm^3): "
                         "too many for memory; lower the density or the volume")
    idx = np.indices(n).reshape(3, -1).T
    pos = np.array([b[0], b[2], b[4]]) + (idx + rng.uniform(0.0, 1.0, (total, 3))) * (L / n)
    return Scatterers3D(pos, rng.standard_normal(total))


def _taps(coord, n, half):
    start = np.floor(coord).astype(np.int64) - half + 1
    idx = start[:, None] + np.arange(2 * half, dtype=np.int64)[None, :]
    return idx, (idx >= 0) & (idx < n)


def render_volume(positions, amplitudes, grid: ImagingVolume, psf: PSF3D | None = None, *,
                  chunk_bytes: float = 64e6, dtype=np.float32) -> np.ndarray:
    """Noise-free RF volume of point scatterers at exact positions (module docstring for the scheme).

    Parameters
    ----------
    positions : (N, 3) float, mm
        Scatterer positions [x, y, z].
    amplitudes : (N,) float
    grid : ImagingVolume
    psf : PSF3D, optional (default :class:`PSF3D`)
    chunk_bytes : float
        Memory of one block of sub-plane images (the working set).
    dtype : numpy dtype of the result (float32 default).

    Returns
    -------
    (n_axial, n_lateral, n_elevational) RF.
    """
    psf = PSF3D() if psf is None else psf
    pos = np.asarray(positions, dtype=float)
    amp = np.asarray(amplitudes, dtype=float)
    if pos.ndim != 2 or pos.shape[1] != 3 or amp.shape != (pos.shape[0],):
        raise ValueError(f"positions must be (N, 3) and amplitudes (N,), got {pos.shape} and {amp.shape}")
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(amp))):
        raise ValueError("scatterer positions and amplitudes must be finite")
    nx, ny, nz = grid.shape
    dx, dy, dz = grid.spacing
    x0, y0, z0 = grid.origin
    depth_max = x0 + nx * dx
    hx, hy, hz = psf.half_support_mm(depth_max)
    kx = max(1, int(math.ceil(hx / dx)))
    ky = max(1, int(math.ceil(hy / dy)))
    fx = (pos[:, 0] - x0) / dx
    fy = (pos[:, 1] - y0) / dy
    z_lo, z_hi = z0 - hz, z0 + (nz - 1) * dz + hz
    keep = ((fx > -kx) & (fx < nx - 1 + kx) & (fy > -ky) & (fy < ny - 1 + ky)
            & (pos[:, 2] > z_lo) & (pos[:, 2] < z_hi))
    pos, amp, fx, fy = pos[keep], amp[keep], fx[keep], fy[keep]
    out = np.zeros(grid.shape, dtype=np.float64)
    if len(amp) == 0:
        return out.astype(dtype)
    # elevational sub-planes, spacing <= sigma_z(min) / 8, each scatterer split linearly between two
    s_min = float(np.min(psf.sigma_elevational_mm(np.array([x0, depth_max, psf.elevational_focus_mm or x0]))))
    dsub = s_min / 8.0
    n_sub = int(math.ceil((z_hi - z_lo) / dsub)) + 2
    zs = z_lo + dsub * np.arange(n_sub)
    fz = (pos[:, 2] - z_lo) / dsub
    m0 = np.clip(np.floor(fz).astype(np.int64), 0, n_sub - 2)
    t = fz - m0
    # depth bands for the elevational beam (its width changes by < 1 % across a band)
    band = max(1, min(nx, int(round(1.0 / dx)) if psf.elevational_focus_mm is not None else nx))
    nb = -(-nx // band)
    xb = x0 + dx * (np.arange(nb) * band + 0.5 * (band - 1))
    zk = grid.z
    order = np.argsort(m0, kind="stable")
    m0s = m0[order]
    per_sub = 4.0 * nx * ny
    step = max(2, int(chunk_bytes // per_sub))
    for c0 in range(0, n_sub - 1, step):
        c1 = min(n_sub - 1, c0 + step)             # scatterers with m0 in [c0, c1) touch sub-planes c0..c1
        a, b = np.searchsorted(m0s, [c0, c1])
        if a == b:
            continue
        sel = order[a:b]
        n = len(sel)
        ncol = c1 - c0 + 1
        # axial factors (exact, amplitude folded in) and lateral factors at the scatterer's depth
        ix, vx = _taps(fx[sel], nx, kx)
        ax = psf.axial((ix - fx[sel, None]) * dx) * amp[sel, None]
        ax[~vx] = 0.0
        ix[~vx] = 0
        iy, vy = _taps(fy[sel], ny, ky)
        lat = psf.lateral((iy - fy[sel, None]) * dy, pos[sel, 0:1])
        lat[~vy] = 0.0
        iy[~vy] = 0
        A = sp.csr_matrix(sp.csc_matrix((ax.ravel(), ix.ravel(), np.arange(0, n * 2 * kx + 1, 2 * kx)),
                                        shape=(nx, n)))
        lo = (m0[sel] - c0)[:, None] * ny + iy
        ts = t[sel, None]
        L = sp.csr_matrix((np.concatenate([lat * (1.0 - ts), lat * ts], axis=1).ravel(),
                           np.concatenate([lo, lo + ny], axis=1).ravel(), np.arange(0, n * 4 * ky + 1, 4 * ky)),
                          shape=(n, ncol * ny))
        del ax, ix, lat, iy
        P = (A @ L).toarray().astype(np.float32).reshape(nx, ncol, ny)   # sub-plane images
        Pz = np.ascontiguousarray(P.transpose(0, 2, 1))                   # (nx, ny, ncol)
        del P
        dz_off = zk[None, :] - zs[c0:c1 + 1, None]                        # (ncol, nz)
        kk = np.flatnonzero(np.any(np.abs(dz_off) <= hz, axis=0))        # output planes this block reaches
        if kk.size == 0:
            continue
        k0, k1 = kk[0], kk[-1] + 1
        dz_off = dz_off[:, k0:k1]
        for bi in range(nb):
            r0, r1 = bi * band, min(nx, (bi + 1) * band)
            H = psf.elevational(dz_off, xb[bi])
            H[np.abs(dz_off) > hz] = 0.0
            out[r0:r1, :, k0:k1] += (Pz[r0:r1].reshape(-1, ncol) @ H.astype(np.float32)).reshape(
                r1 - r0, ny, k1 - k0)
    return out.astype(dtype, copy=False)


# --------------------------------------------------------------------------------------------------------------
# 3D displacement fields
# --------------------------------------------------------------------------------------------------------------

def _sym6(G) -> np.ndarray:
    """(n, 3, 3) gradient [component, derivative] -> (n, 6) small strain in :data:`STRAIN_COMPONENTS_3D` order."""
    return np.stack([G[:, 0, 0], G[:, 1, 1], G[:, 2, 2], 0.5 * (G[:, 0, 1] + G[:, 1, 0]),
                     0.5 * (G[:, 0, 2] + G[:, 2, 0]), 0.5 * (G[:, 1, 2] + G[:, 2, 1])], axis=1)


def _points3(points) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must be (n, 3) [x, y, z] mm, got shape {p.shape}")
    return p


def _rotation(angles_deg) -> np.ndarray:
    """Rotation matrix of small or large angles (deg) about the x, y, z axes, applied in that order."""
    ax, ay, az = np.radians(np.asarray(angles_deg, float))
    Rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    Ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    Rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


class Affine3D:
    """Exact affine 3D field ``u(X) = (F - I)(X - centre) + translation``.

    ``F = R (C + S)``: ``C = diag(1 - c, s, s)`` an axial compression by ``compression`` (fraction, > 0 shortens
    along x) with the incompressible lateral and elevational expansion ``s = (1 - c)^(-1/2)`` (det C = 1);
    ``S`` the simple shears ``shear = {"xy": g, "xz": g, "yz": g}`` (``S[0, 1] = g`` moves x in proportion to
    y, ...); ``R`` the rotation by ``rotation_deg`` = (about x, about y, about z) degrees.  ``strain`` is the
    small strain ``sym(F - I)`` (n, 6) in :data:`STRAIN_COMPONENTS_3D` order, which is what a registration of
    the pair measures as ``sym grad u``.
    """

    def __init__(self, compression: float = 0.01, *, shear=None, rotation_deg=(0.0, 0.0, 0.0),
                 centre=(10.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0), name: str = "affine3d"):
        c = float(compression)
        if not (math.isfinite(c) and -0.5 < c < 0.5):
            raise ValueError(f"compression must be a fraction in (-0.5, 0.5), got {compression!r}")
        s = (1.0 - c) ** -0.5
        C = np.diag([1.0 - c, s, s])
        S = np.zeros((3, 3))
        idx = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2), "yx": (1, 0), "zx": (2, 0), "zy": (2, 1)}
        for k, g in dict(shear or {}).items():
            if k not in idx:
                raise ValueError(f"unknown shear {k!r}: expected one of {tuple(idx)}")
            S[idx[k]] = float(g)
        self.F = _rotation(rotation_deg) @ (C + S)
        self.centre = np.asarray(centre, float).reshape(3)
        self.translation = np.asarray(translation, float).reshape(3)
        self.name = str(name)

    def gradient(self) -> np.ndarray:
        """``F - I`` (3, 3), ``[i, j] = du_i / dX_j``."""
        return self.F - np.eye(3)

    def displacement(self, points) -> np.ndarray:
        p = _points3(points)
        return (p - self.centre) @ self.gradient().T + self.translation

    def strain(self, points) -> np.ndarray:
        p = _points3(points)
        return np.repeat(_sym6(self.gradient()[None]), len(p), axis=0)

    def __call__(self, points):
        return self.displacement(points)


class FunctionField3D:
    """A plain callable ``u(points (n, 3) mm) -> (n, 3) mm`` as a field; strain by central differences (step
    ``h`` mm, exact for fields up to quadratic)."""

    def __init__(self, fn, name: str = "custom", h: float = 1e-3):
        self.fn, self.name, self.h = fn, str(name), float(h)

    def displacement(self, points) -> np.ndarray:
        p = _points3(points)
        u = np.asarray(self.fn(p), float)
        if u.shape != p.shape:
            raise ValueError(f"displacement callable must return shape {p.shape}, got {u.shape}")
        return u

    def strain(self, points) -> np.ndarray:
        p = _points3(points)
        G = np.empty((len(p), 3, 3))
        for j in range(3):
            e = np.zeros(3)
            e[j] = self.h
            G[:, :, j] = (self.displacement(p + e) - self.displacement(p - e)) / (2 * self.h)
        return _sym6(G)

    def __call__(self, points):
        return self.displacement(points)


class FEVolumeField:
    """A 3D forward solution (:func:`forward.elasticity.solve_elasticity` ``model="3d"``) scaled by ``scale``
    (the solution is at 1 mm patch compression): ``displacement`` (n, 3) from ``Solution.displacement_3d``,
    ``strain`` (n, 6) from the full 3D P2 gradient, NaN outside the block; ``inside`` is the inclusion."""

    def __init__(self, solution, scale: float = 1.0, name: str = "fe3d"):
        if getattr(solution, "dim", None) != 3:
            raise ValueError("FEVolumeField needs a 3d forward solution (solve_elasticity(model='3d'))")
        self.solution, self.scale, self.name = solution, float(scale), str(name)

    def displacement(self, points, chunk: int = 250_000) -> np.ndarray:
        p = _points3(points)
        out = np.empty((len(p), 3))
        for a in range(0, len(p), chunk):
            out[a:a + chunk] = self.solution.displacement_3d(p[a:a + chunk])
        return self.scale * out

    def gradient(self, points, chunk: int = 250_000) -> np.ndarray:
        """Displacement gradient (n, 3, 3) ``[i, j] = du_i / dX_j``."""
        p = _points3(points)
        sol = self.solution
        out = np.full((len(p), 3, 3), np.nan)
        for a in range(0, len(p), chunk):
            q, sgn, elem, X, inside = sol._eval(p[a:a + chunk], "nan", ncoord=3)
            if np.any(inside):
                g = sol._values(elem[inside], X[inside], grad=True)
                blk = out[a:a + chunk]
                blk[inside] = sol._mirror(g, sgn[inside], True)
        return self.scale * out

    def strain(self, points) -> np.ndarray:
        return _sym6(self.gradient(points))

    def inside(self, points) -> np.ndarray:
        """Points inside the spherical inclusion (centre on the axis at the solve's inclusion depth)."""
        p = _points3(points)
        prm = self.solution.params
        r = 0.5 * float(prm.get("inclusion_diameter_mm", 15.0))
        d = p - np.array([float(prm.get("inclusion_depth_mm", 30.0)), 0.0, 0.0])
        return np.einsum("ij,ij->i", d, d) < r * r

    def __call__(self, points):
        return self.displacement(points)


def _as_field3(f):
    if callable(getattr(f, "displacement", None)):
        return f
    if callable(f):
        return FunctionField3D(f)
    raise ValueError("field must be a callable points (n, 3) -> (n, 3) mm or have a displacement() method")


class _Zero:
    name = "zero"

    def displacement(self, points):
        return np.zeros_like(_points3(points))


# --------------------------------------------------------------------------------------------------------------
# pairs and sequences
# --------------------------------------------------------------------------------------------------------------

@dataclass
class VolumeSequence:
    """RF volumes of the same scatterers moved by a field per frame, with exact truth.

    ``frames`` (n, n_axial, n_lateral, n_elevational) float32 (frame 0 the reference), ``grid`` the
    :class:`ImagingVolume` (``spacing``, ``origin``), ``fields`` the field of each frame (frame 0 -> k,
    frame-0 coordinates, ``frames[0](x) ~ frames[k](x + u(x))``), ``params`` every parameter and timing.
    """

    frames: np.ndarray
    grid: ImagingVolume
    fields: list
    params: dict = dc_field(default_factory=dict)
    path: Path | None = None

    @property
    def spacing(self):
        return self.grid.spacing

    @property
    def origin(self):
        return self.grid.origin

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    def voxel_points(self) -> np.ndarray:
        return self.grid.points()

    def true_displacement(self, k: int, points) -> np.ndarray:
        """True displacement frame 0 -> ``k`` at frame-0 points (n, 3) -> (n, 3) mm."""
        return np.asarray(self.fields[k].displacement(_points3(points)), float)

    def true_strain(self, k: int, points) -> np.ndarray:
        """True small strain frame 0 -> ``k`` (n, 6) ordered exx, eyy, ezz, exy, exz, eyz."""
        return np.asarray(self.fields[k].strain(_points3(points)), float)


@dataclass
class VolumePair(VolumeSequence):
    """A reference / moving volume pair (:class:`VolumeSequence` of two frames): ``ref``, ``mov``, ``field``."""

    @property
    def ref(self) -> np.ndarray:
        return self.frames[0]

    @property
    def mov(self) -> np.ndarray:
        return self.frames[1]

    @property
    def field(self):
        return self.fields[1]


def _seed(seed) -> int:
    if isinstance(seed, bool) or int(seed) != seed or int(seed) < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


def _snr(snr_db):
    if snr_db is None:
        return None
    v = float(snr_db)
    if not math.isfinite(v):
        raise ValueError(f"snr_db must be finite (or None for no noise), got {snr_db!r}")
    return v


def _render_frames(fields, grid, psf, scat, snr_db, rng_noise, log, u_cache=None, echo_gain_db=None,
                   tgc_db=None):
    gain = _depth_gain(echo_gain_db, grid, "echo_gain_db")
    tgc = _depth_gain(tgc_db, grid, "tgc_db")
    frames = np.empty((len(fields),) + grid.shape, np.float32)
    sigma, t_render = 0.0, 0.0
    noise_rngs = [np.random.default_rng(s) for s in rng_noise.spawn(len(fields))]
    for k, f in enumerate(fields):
        u = u_cache(k) if u_cache is not None else np.asarray(f.displacement(scat.positions), float)
        if not np.all(np.isfinite(u)):
            raise ValueError(f"field {getattr(f, 'name', f)!r} is not finite at the scatterers")
        t0 = time.perf_counter()
        clean = render_volume(scat.positions + u, scat.amplitudes, grid, psf, dtype=np.float64)
        t_render += time.perf_counter() - t0
        if k == 0 and snr_db is not None:
            sigma = noise_sigma(float(np.mean(clean ** 2)), snr_db)
        if gain is not None:        # after the noise level: snr_db stays the SNR at 0 dB gain
            clean *= gain[:, None, None]
        if sigma > 0:
            clean += sigma * noise_rngs[k].standard_normal(clean.shape)
        if tgc is not None:         # the receiver's gain: echo and noise alike
            clean *= tgc[:, None, None]
        frames[k] = clean
        log(f"  volume {k + 1}/{len(fields)} rendered")
    return frames, sigma, t_render


def make_volume_sequence(fields, probe="matrix7", size_mm=(20.0, 20.0, 15.0), *, top_mm: float = 2.0,
                         snr_db: float | None = 30.0, seed: int = 0, density_per_mm3: float | None = None,
                         amplitude_factor_inside: float = 2.0, verbose: bool = False, echo_gain_db=None,
                         tgc_db=None) -> VolumeSequence:
    """Render frame 0 (undeformed) and one volume per field in ``fields`` (each a callable (n, 3) -> (n, 3) mm
    or an object with ``displacement``; frame-0 -> frame-k fields).

    ``size_mm`` = (depth, width, elevation) from ``top_mm`` down, centred laterally and elevationally, sampled at
    the probe's spacing.  Scatterers fill the volume plus the PSF support plus the largest displacement plus
    0.5 mm (tissue only at x >= 0), density ``density_per_mm3`` (default: :data:`SCATTERERS_PER_CELL_3D` per
    ``sigma_x sigma_y sigma_z``), amplitudes doubled where a field's ``inside(points)`` is true.  Noise: white
    Gaussian, ``SNR = 10 log10(mean(clean frame 0 ^2) / sigma^2)``, the same sigma in every frame (None: none).
    Seeded (``numpy.random.SeedSequence(seed)``: scatterers, then noise per frame).  ``echo_gain_db`` and
    ``tgc_db`` (callables of depth mm -> dB) as in :func:`forward.pairs.make_pair`: a depth gain of the echo before
    the noise (e.g. :func:`forward.pairs.attenuation_gain_db`, whose echo sinks to the noise floor at
    :func:`forward.pairs.noise_floor_depth`), and of echo and noise alike after it.
    """
    t_start = time.perf_counter()
    log = print if verbose else (lambda *a, **k: None)
    pr = as_volume_probe(probe)
    psf = pr.psf()
    fields = [_as_field3(f) for f in (fields if isinstance(fields, (list, tuple)) else [fields])]
    snr_db = _snr(snr_db)
    seed = _seed(seed)
    grid = ImagingVolume.centred(size_mm, pr.spacing, top_mm=positive("top_mm", top_mm) if top_mm else 0.0)
    ext = grid.extent()
    hx, hy, hz = psf.half_support_mm(ext[1])
    g = [np.linspace(max(0.0, ext[0] - hx), ext[1] + hx, 13), np.linspace(ext[2] - hy, ext[3] + hy, 13),
         np.linspace(ext[4] - hz, ext[5] + hz, 13)]
    P = np.column_stack([a.ravel() for a in np.meshgrid(*g, indexing="ij")])
    umax = np.zeros(3)
    for f in fields:
        u = np.asarray(f.displacement(P), float)
        if not np.all(np.isfinite(u)):
            raise ValueError(f"field {getattr(f, 'name', f)!r} is not finite around the imaged volume")
        umax = np.maximum(umax, np.max(np.abs(u), axis=0))
    m = umax + np.array([hx, hy, hz]) + 0.5
    box = (max(0.0, ext[0] - m[0]), ext[1] + m[0], ext[2] - m[1], ext[3] + m[1], ext[4] - m[2], ext[5] + m[2])
    dens = pr.density_per_mm3() if density_per_mm3 is None else positive("density_per_mm3", density_per_mm3)
    ss_scat, ss_noise = np.random.SeedSequence(seed).spawn(2)
    sig = np.array([psf.sigma_axial_mm, float(psf.sigma_lateral_mm()), float(psf.sigma_elevational_mm())])
    scat = make_scatterers_3d(np.random.default_rng(ss_scat), box, density_per_mm3=dens, cell_aspect=sig)
    for f in fields:
        inside = getattr(f, "inside", None)
        if callable(inside):
            scat.amplitudes[np.asarray(inside(scat.positions), bool)] *= float(amplitude_factor_inside)
            break
    frames, sigma, t_render = _render_frames([_Zero()] + fields, grid, psf, scat, snr_db, ss_noise, log,
                                             echo_gain_db=echo_gain_db, tgc_db=tgc_db)
    params = dict(probe=pr.to_dict(), psf=psf.to_dict(), size_mm=[float(s) for s in size_mm],
                  top_mm=float(top_mm), snr_db=snr_db, seed=seed, density_per_mm3=dens, n_scatterers=len(scat),
                  scatterer_box_mm=[float(b) for b in box], noise_sigma=sigma, grid=grid.to_dict(),
                  fields=[getattr(f, "name", "custom") for f in fields],
                  timings_s=dict(render=t_render, total=time.perf_counter() - t_start))
    for key, fn in (("echo_gain_db", echo_gain_db), ("tgc_db", tgc_db)):
        if fn is not None:
            params[key] = [float(v) for v in 20.0 * np.log10(_depth_gain(fn, grid, key))]
    return VolumeSequence(frames=frames, grid=grid, fields=[_Zero()] + fields, params=params)


def make_volume_pair(field, probe="matrix7", size_mm=(20.0, 20.0, 15.0), **kwargs) -> VolumePair:
    """A reference / moving volume pair related by ``field`` (:func:`make_volume_sequence` with one field):
    ``pair.ref``, ``pair.mov``, ``pair.spacing``, ``pair.origin``, ``pair.field``; ``reference(x) ~
    moving(x + u(x))``."""
    seq = make_volume_sequence([field], probe, size_mm, **kwargs)
    return VolumePair(frames=seq.frames, grid=seq.grid, fields=seq.fields, params=seq.params)


# --------------------------------------------------------------------------------------------------------------
# The paper's 3D phantom imaged as volumes
# --------------------------------------------------------------------------------------------------------------

class ScaledField:
    """``scale * U(X)`` with ``U`` a unit field (e.g. the unit-compression FE field, evaluated once at the
    scatterers): ``displacement``, ``strain`` and ``inside`` of ``base`` scaled; ``name`` for the params."""

    def __init__(self, base, scale, name):
        self.base, self.scale, self.name = base, float(scale), name

    def displacement(self, points):
        return self.scale * self.base.displacement(points)

    def strain(self, points):
        return self.scale * self.base.strain(points)

    def inside(self, points):
        return self.base.inside(points)


def _paper_key(inclusion, kwargs) -> str:
    from .elasticity import cache_key
    from .sequences import BACKGROUND_MODULUS, INCLUSIONS

    fe = cache_key("3d", inclusion_modulus=INCLUSIONS[inclusion], background_modulus=BACKGROUND_MODULUS,
                   inclusion_depth_mm=30.0, inclusion_diameter_mm=15.0, compression_mm=1.0,
                   **kwargs.get("fe_options", {}))
    blob = json.dumps(dict(kwargs, inclusion=inclusion, fe=fe, version=VOLUME_FORMAT_VERSION), sort_keys=True,
                      default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def paper_volume_sequence(inclusion: str = "HI", *, frames=(0, 6), probe="paper3d", depth_mm: float = 72.0,
                          width_mm: float = 44.0, elevation_mm: float = 20.0, snr_db: float | None = 12.0,
                          seed: int = 0, density_per_mm3: float | None = None, fe_options: dict | None = None,
                          cache_dir=None, refresh: bool = False, verbose: bool = False) -> VolumeSequence:
    """The paper's 3D phantom (HI, SI, mHI, HOM) imaged as RF volumes under its compression schedule.

    The volume covers the paper's imaged plane (``depth_mm`` 72 from the top face x = 0 by ``width_mm`` 44
    lateral) and ``+- elevation_mm / 2`` (default +-10 mm) elevationally around it, with an odd number of
    elevational planes so that one is the imaging plane z = 0 (the 2D sequences' plane).  Frame ``k`` (index 0 =
    the paper's frame 1) is the unit-compression 3D FE solution (``forward.cached_solve(model="3d")``) scaled so
    that the mean axial strain over the imaged *plane* follows :func:`forward.sequences.paper_schedule`, the same
    scales as the 2D :func:`forward.sequences.simulate_sequence` of the 3D model; ``frames`` selects which are
    rendered (default ``(0, 6)``: the paper's frames 1 and 7, the single-frame pair of its alpha selection).
    Scatterers, noise and the doubled amplitude in the inclusion as the paper.  Cached on disk
    (:func:`forward.elasticity.cache_dir` ``/volumes``) by a hash of every argument; ``refresh=True`` re-renders.

    Returns a :class:`VolumeSequence` with ``params["frames"]`` the paper indices rendered and
    ``params["scales"]`` the patch compression (mm) of each rendered frame; ``fields`` are exact
    (:class:`FEVolumeField` scaled).
    """
    from .elasticity import cache_dir as _root, cached_solve
    from .sequences import BACKGROUND_MODULUS, INCLUSIONS, _check_inclusion, paper_schedule

    _check_inclusion(inclusion)
    idx = [int(k) for k in frames]
    if not idx or min(idx) < 0 or max(idx) > 19:
        raise ValueError(f"frames must be paper frame indices in 0..19, got {frames!r}")
    pr = as_volume_probe(probe)
    kw = dict(frames=idx, probe=pr.to_dict(), depth_mm=float(depth_mm), width_mm=float(width_mm),
              elevation_mm=float(elevation_mm), snr_db=_snr(snr_db), seed=_seed(seed),
              density_per_mm3=density_per_mm3, fe_options=dict(fe_options or {}))
    folder = Path(cache_dir) if cache_dir is not None else _root() / "volumes"
    path = folder / f"3d-{inclusion}_vol_seed{seed}_{_paper_key(inclusion, kw)}.npz"
    log = print if verbose else (lambda *a, **k: None)
    sol = cached_solve("3d", inclusion_modulus=INCLUSIONS[inclusion], background_modulus=BACKGROUND_MODULUS,
                       inclusion_depth_mm=30.0, inclusion_diameter_mm=15.0, compression_mm=1.0,
                       **dict(fe_options or {}))
    unit = FEVolumeField(sol, 1.0, name=f"3d-{inclusion}")
    if path.is_file() and not refresh:
        try:
            return load_volume_sequence(path, unit)
        except (ValueError, OSError, KeyError):
            pass
    t_start = time.perf_counter()
    # scales: the mean exx over the imaged plane (as the 2D sequence of the 3D model)
    grid = ImagingVolume.centred((depth_mm, width_mm, elevation_mm), pr.spacing, top_mm=0.0)
    nz = 2 * int(round(0.5 * float(elevation_mm) / pr.spacing[2])) + 1     # odd: a plane at z = 0, the 2D plane
    grid = ImagingVolume((grid.shape[0], grid.shape[1], nz), grid.spacing,
                         (grid.origin[0], grid.origin[1], -0.5 * (nz - 1) * pr.spacing[2]))
    Xp, Yp = np.meshgrid(grid.x, grid.y, indexing="ij")
    plane = np.column_stack([Xp.ravel()[::5], Yp.ravel()[::5], np.zeros(Xp.size)[::5]])
    mean_exx = float(np.nanmean(unit.strain(plane)[:, 0]))
    if not mean_exx < 0:
        raise ValueError(f"the 3D forward field does not compress the imaged plane (mean exx {mean_exx:g})")
    scales = paper_schedule(max(idx) + 1)[idx] / -mean_exx
    psf = pr.psf()
    ext = grid.extent()
    hx, hy, hz = psf.half_support_mm(ext[1])
    s_max = float(np.max(scales))
    m = np.array([s_max * 1.2 + hx, s_max * 0.6 + hy, s_max * 0.6 + hz]) + 0.5
    box = (0.0, ext[1] + m[0], ext[2] - m[1], ext[3] + m[1], ext[4] - m[2], ext[5] + m[2])
    dens = pr.density_per_mm3() if density_per_mm3 is None else positive("density_per_mm3", density_per_mm3)
    ss_scat, ss_noise = np.random.SeedSequence(_seed(seed)).spawn(2)
    sig = np.array([psf.sigma_axial_mm, float(psf.sigma_lateral_mm()), float(psf.sigma_elevational_mm())])
    scat = make_scatterers_3d(np.random.default_rng(ss_scat), box, density_per_mm3=dens, cell_aspect=sig)
    t0 = time.perf_counter()
    U = unit.displacement(scat.positions)
    ok = np.all(np.isfinite(U), axis=1)
    scat = Scatterers3D(scat.positions[ok], scat.amplitudes[ok])
    U = U[ok]
    scat.amplitudes[unit.inside(scat.positions)] *= 2.0
    t_field = time.perf_counter() - t0
    log(f"  {len(scat)} scatterers, FE displacement {t_field:.1f} s")
    fields = [ScaledField(unit, s, f"3d-{inclusion} x{s:.4f}") for s in scales]
    vol, sigma, t_render = _render_frames(fields, grid, psf, scat, _snr(snr_db), ss_noise, log,
                                          u_cache=lambda k: scales[k] * U)
    params = dict(kw, inclusion=inclusion, scales=[float(s) for s in scales], mean_exx_unit=mean_exx,
                  strain_schedule=[float(v) for v in paper_schedule(max(idx) + 1)[idx]], psf=psf.to_dict(),
                  n_scatterers=len(scat), density=dens, noise_sigma=sigma, grid=grid.to_dict(),
                  timings_s=dict(fe_displacement=t_field, render=t_render, total=time.perf_counter() - t_start))
    seq = VolumeSequence(frames=vol, grid=grid, fields=fields, params=params)
    from femreg.io import atomic_savez

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_savez(path, writer=lambda tmp: np.savez(tmp, frames=vol, meta=np.array(json.dumps(params))))
    seq.path = path
    return seq


def load_volume_sequence(path, unit_field=None) -> VolumeSequence:
    """Read a volume sequence written by :func:`paper_volume_sequence`; ``unit_field`` (the unit-compression
    field) restores its exact ``fields``."""
    with np.load(path, allow_pickle=False) as z:
        frames = z["frames"]
        params = json.loads(str(z["meta"]))
    g = params["grid"]
    grid = ImagingVolume(tuple(g["shape"]), tuple(g["spacing"]), tuple(g["origin"]))
    if frames.shape[1:] != grid.shape or len(params["scales"]) != frames.shape[0]:
        raise ValueError(f"{path}: frames {frames.shape} do not match the grid {grid.shape}")
    fields = ([ScaledField(unit_field, s, f"x{s:.4f}") for s in params["scales"]] if unit_field is not None
              else [])
    return VolumeSequence(frames=frames, grid=grid, fields=fields, params=params, path=Path(path))


def central_plane(volume, grid: ImagingVolume, z_mm: float = 0.0):
    """The (axial, lateral) plane of ``volume`` nearest ``z_mm`` and its elevation: ``(image, z)``."""
    k = int(np.argmin(np.abs(grid.z - float(z_mm))))
    return np.asarray(volume)[:, :, k], float(grid.z[k])
