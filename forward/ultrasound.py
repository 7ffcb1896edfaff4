"""RF ultrasound image formation: separable spatially invariant PSF, point scatterers, noise, B-mode.

This is the paper's simulator (section "Simulated data"): a 2D spatially invariant point spread function (PSF)
convolved with point scatterers, sampled at 40 MHz axially (0.01925 mm at 1540 m/s) and 0.3 mm laterally, with
white Gaussian noise added to a stated SNR.

Coordinates (mm): ``x`` = depth below the top face (axial, the beam direction), ``y`` = lateral offset from the
centre line.  Images are arrays ``(n_axial, n_lateral)``; pixel ``[i, j]`` has its centre at
``origin + (i * dx, j * dy)``.

PSF (:class:`PSF`)
------------------
Separable, ``h(x, y) = h_ax(x) * h_lat(y)`` with, for a scatterer at ``(x_s, y_s)``,

.. math::

    h_{ax}(x) = \\exp\\!\\left(-\\frac{(x - x_s)^2}{2\\sigma_x^2}\\right)\\cos\\!\\left(\\frac{4\\pi f_0 (x - x_s)}{c}\\right),
    \\qquad
    h_{lat}(y) = \\exp\\!\\left(-\\frac{(y - y_s)^2}{2\\sigma_y^2}\\right).

The axial coordinate is depth, so echo time is ``t = 2 x / c`` (round trip) and the carrier has period
``c / (2 f0)`` = 0.14 mm in depth for f0 = 5.5 MHz.

*Pulse length*: the paper's "Gaussian modulated pulse length of 0.43 us" is taken as the **-6 dB (full width at
half maximum) duration of the Gaussian envelope in echo time**: ``T = 2 sqrt(2 ln 2) sigma_t`` with ``T = 0.43 us``,
so ``sigma_t = 0.1826 us`` and, in depth, ``sigma_x = c sigma_t / 2 = 0.1406 mm`` (axial -6 dB resolution
0.331 mm; -6 dB fractional bandwidth of the amplitude spectrum 37 %).  The lateral FWHM 1.4 mm is the full width at
half maximum of the *amplitude* (envelope) profile, ``sigma_y = 1.4 / (2 sqrt(2 ln 2)) = 0.5945 mm``.

Both factors are evaluated analytically at the exact offsets ``x_i - x_s`` and ``y_j - y_s`` (no snapping of the
scatterer to the pixel grid), truncated at ``truncation`` standard deviations (default 4: relative error < 4e-4).

Rendering (:func:`render_rf`)
-----------------------------
``RF = A diag(a) L`` with ``A`` (n_axial, N) sparse, ``A[i, s] = h_ax(x_i - x_s)`` (about 60 nonzeros per column),
``L`` (N, n_lateral) sparse, ``L[s, j] = h_lat(y_j - y_s)`` (16 nonzeros per row): one sparse-sparse product per
frame, O(N * 60 * 16) operations, no per-scatterer Python loop.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import scipy.sparse as sp

from femreg.plot import bmode  # noqa: F401  (the one B-mode and the one envelope, re-exported)
from femreg.speckle import envelope  # noqa: F401

__all__ = [
    "SPEED_OF_SOUND_MM_PER_S", "PSF", "ImagingGrid", "Scatterers", "make_scatterers", "render_rf",
    "noise_sigma", "add_noise", "envelope", "bmode", "measured_snr_db",
]

#: Speed of sound, mm/s (1540 m/s).
SPEED_OF_SOUND_MM_PER_S = 1.54e6
_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


def positive(name: str, value) -> float:
    """``value`` as a float, or ValueError naming ``name`` unless it is a positive finite number."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


@dataclass(frozen=True)
class PSF:
    """Separable, spatially invariant RF point spread function (see the module docstring for the formulas).

    Parameters
    ----------
    center_frequency_hz : float
        Carrier (centre) frequency f0, Hz.  Paper: 5.5 MHz.
    pulse_length_s : float
        -6 dB (FWHM) duration of the Gaussian envelope in echo time, s.  Paper: 0.43 us.
    lateral_fwhm_mm : float
        FWHM of the lateral amplitude profile, mm.  Paper: 1.4 mm.
    speed_of_sound_mm_per_s : float
        c, mm/s.  Paper: 1540 m/s.
    truncation : float
        Support of each factor in standard deviations (each side).
    """

    center_frequency_hz: float = 5.5e6
    pulse_length_s: float = 0.43e-6
    lateral_fwhm_mm: float = 1.4
    speed_of_sound_mm_per_s: float = SPEED_OF_SOUND_MM_PER_S
    truncation: float = 4.0

    def __post_init__(self):
        for name in ("center_frequency_hz", "pulse_length_s", "lateral_fwhm_mm", "speed_of_sound_mm_per_s",
                     "truncation"):
            object.__setattr__(self, name, positive(name, getattr(self, name)))

    @property
    def sigma_t_s(self) -> float:
        """Standard deviation of the envelope in echo time, s."""
        return self.pulse_length_s / _FWHM_PER_SIGMA

    @property
    def sigma_axial_mm(self) -> float:
        """Standard deviation of the envelope in depth, mm (``c sigma_t / 2``)."""
        return self.speed_of_sound_mm_per_s * self.sigma_t_s / 2.0

    @property
    def sigma_lateral_mm(self) -> float:
        """Standard deviation of the lateral Gaussian, mm."""
        return self.lateral_fwhm_mm / _FWHM_PER_SIGMA

    @property
    def carrier_period_mm(self) -> float:
        """Period of the carrier in depth, ``c / (2 f0)``, mm."""
        return self.speed_of_sound_mm_per_s / (2.0 * self.center_frequency_hz)

    def axial(self, d_mm):
        """Axial factor ``h_ax`` at depth offsets ``d_mm`` (any shape), peak 1 at 0."""
        d = np.asarray(d_mm, dtype=float)
        return np.exp(-0.5 * (d / self.sigma_axial_mm) ** 2) * np.cos((2.0 * np.pi / self.carrier_period_mm) * d)

    def lateral(self, d_mm):
        """Lateral factor ``h_lat`` at lateral offsets ``d_mm`` (any shape), peak 1 at 0."""
        d = np.asarray(d_mm, dtype=float)
        return np.exp(-0.5 * (d / self.sigma_lateral_mm) ** 2)

    def half_support_mm(self) -> tuple[float, float]:
        """(axial, lateral) half-width of the truncated support, mm."""
        return self.truncation * self.sigma_axial_mm, self.truncation * self.sigma_lateral_mm

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class ImagingGrid:
    """Regular pixel grid of an RF image: pixel ``[i, j]`` centre at ``(x0 + i dx, y0 + j dy)`` mm.

    Parameters
    ----------
    n_axial, n_lateral : int
        Image shape (axial, lateral).
    dx, dy : float
        Axial and lateral pixel spacing, mm (> 0).
    x0, y0 : float
        Centre of pixel ``[0, 0]``, mm.
    """

    n_axial: int
    n_lateral: int
    dx: float
    dy: float
    x0: float = 0.0
    y0: float = 0.0

    def __post_init__(self):
        for name in ("dx", "dy"):
            object.__setattr__(self, name, positive(f"spacing {name} (mm)", getattr(self, name)))
        for name in ("n_axial", "n_lateral"):
            v = getattr(self, name)
            if int(v) != v or int(v) < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        for name in ("x0", "y0"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise ValueError(f"origin {name} must be finite, got {v!r}")
            object.__setattr__(self, name, v)

    @classmethod
    def centred(cls, *, depth_mm: float = 72.0, width_mm: float = 44.0, spacing=None,
                sampling_frequency_hz: float = 40e6, speed_of_sound_mm_per_s: float = SPEED_OF_SOUND_MM_PER_S,
                lateral_spacing_mm: float = 0.3, top_mm: float = 0.0) -> "ImagingGrid":
        """The paper's imaging grid: ``depth_mm`` from ``top_mm`` down, ``width_mm`` centred laterally on y = 0.

        The axial spacing is ``c / (2 fs)`` (0.01925 mm for 40 MHz at 1540 m/s) unless ``spacing=(dx, dy)`` is
        given.  ``n_axial = round(depth / dx)`` pixels from ``x = top_mm``; ``n_lateral = round(width / dy)``
        pixels (at least 1) centred on ``y = 0``.  Paper values: 3740 x 147 pixels.
        """
        depth_mm = positive("depth_mm", depth_mm)
        width_mm = positive("width_mm", width_mm)
        if spacing is None:
            fs = positive("sampling_frequency_hz", sampling_frequency_hz)
            c = positive("speed_of_sound_mm_per_s", speed_of_sound_mm_per_s)
            spacing = (c / (2.0 * fs), lateral_spacing_mm)
        try:
            dx, dy = (float(s) for s in spacing)
        except (TypeError, ValueError):
            raise ValueError(f"spacing must be a pair (dx, dy) of positive mm, got {spacing!r}") from None
        for name, v in (("dx", dx), ("dy", dy)):
            if not math.isfinite(v) or v <= 0:
                raise ValueError(f"spacing {name} must be a positive finite number of mm, got {v!r}")
        n_ax = max(1, int(round(depth_mm / dx)))
        n_lat = max(1, int(round(width_mm / dy)))
        return cls(n_ax, n_lat, dx, dy, float(top_mm), -0.5 * (n_lat - 1) * dy)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_axial, self.n_lateral)

    @property
    def spacing(self) -> tuple[float, float]:
        return (self.dx, self.dy)

    @property
    def origin(self) -> tuple[float, float]:
        return (self.x0, self.y0)

    @property
    def x(self) -> np.ndarray:
        """Axial pixel-centre coordinates, (n_axial,) mm."""
        return self.x0 + self.dx * np.arange(self.n_axial)

    @property
    def y(self) -> np.ndarray:
        """Lateral pixel-centre coordinates, (n_lateral,) mm."""
        return self.y0 + self.dy * np.arange(self.n_lateral)

    def points(self) -> np.ndarray:
        """All pixel centres, (n_axial * n_lateral, 2) [x, y] mm, in C order of the image."""
        X, Y = np.meshgrid(self.x, self.y, indexing="ij")
        return np.column_stack([X.ravel(), Y.ravel()])

    def extent(self) -> tuple[float, float, float, float]:
        """Pixel-edge bounding box ``(x_min, x_max, y_min, y_max)``, mm."""
        return (self.x0 - self.dx / 2, self.x0 + (self.n_axial - 0.5) * self.dx,
                self.y0 - self.dy / 2, self.y0 + (self.n_lateral - 0.5) * self.dy)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Scatterers:
    """Point scatterers: ``positions`` (n, 2) [x, y] mm and ``amplitudes`` (n,)."""

    positions: np.ndarray
    amplitudes: np.ndarray

    def __len__(self) -> int:
        return len(self.amplitudes)


def make_scatterers(rng: np.random.Generator, box, *, density_per_mm2: float = 30.0,
                    inclusion_center=(30.0, 0.0), inclusion_radius_mm: float | None = 7.5,
                    inclusion_amplitude_factor: float = 2.0, placement: str = "stratified",
                    cell_aspect: float = 1.0) -> Scatterers:
    """Uniformly random, evenly distributed scatterers with zero-mean Gaussian amplitudes (fully developed speckle).

    Parameters
    ----------
    rng : numpy.random.Generator
        Seeded generator (positions drawn first, then amplitudes).
    box : (x_min, x_max, y_min, y_max)
        Rectangle (mm) to fill.
    density_per_mm2 : float
        Scatterer density, per mm^2 (paper: 30).  Must be > 0.
    placement : {"stratified", "poisson"}
        ``"stratified"`` (default; the paper's "evenly distributed"): the box is cut into ``nx x ny`` cells of
        about ``1/density`` mm^2 (axial pitch ``sqrt(cell_aspect / density)``, lateral pitch
        ``1 / sqrt(cell_aspect * density)``, counts rounded to fit the box) and each cell holds one scatterer
        uniformly random inside it: the marginal density is uniform, without the local count fluctuations of
        independent placement.  ``"poisson"``: ``round(density * area)`` independent uniform positions.
    cell_aspect : float
        Axial / lateral pitch of the stratification cells; :func:`forward.sequences.simulate_sequence` uses the
        PSF's ``sigma_axial / sigma_lateral`` (0.24) so each resolution cell spans as many cells axially as
        laterally.
    inclusion_center, inclusion_radius_mm : (float, float), float or None
        Disk (mm) whose scatterers get amplitude x ``inclusion_amplitude_factor`` (paper: x2).  ``None`` radius: none.
    inclusion_amplitude_factor : float
        Amplitude factor inside the inclusion (> 0).

    Notes
    -----
    Amplitudes are standard normal, N(0, 1): given the positions the RF is a Gaussian field whose local power
    is ``sum_s h^2(x - x_s)``.  With independent (Poisson) positions that local power fluctuates with the local
    scatterer count (about 10.5 effective scatterers per resolution cell at 30 per mm^2: relative variance
    ~0.095), which lowers the envelope mean/std from the Rayleigh 1.91 to about 1.81 (measured, 30 x 30 mm).
    Stratified positions with PSF-matched cells remove most of the count fluctuation: about 1.89 measured, i.e.
    fully developed speckle at the paper's density.
    """
    try:
        density = float(density_per_mm2)
    except (TypeError, ValueError):
        raise ValueError(f"density_per_mm2 must be a positive number, got {density_per_mm2!r}") from None
    if not math.isfinite(density) or density <= 0:
        raise ValueError(f"density_per_mm2 must be a positive finite number of scatterers per mm^2, got "
                         f"{density_per_mm2!r}")
    x_min, x_max, y_min, y_max = (float(b) for b in box)
    if not (x_max > x_min and y_max > y_min):
        raise ValueError(f"scatterer box must have x_max > x_min and y_max > y_min, got {box!r}")
    factor = positive("inclusion_amplitude_factor", inclusion_amplitude_factor)
    if placement == "stratified":
        aspect = positive("cell_aspect", cell_aspect)
        nx = max(1, int(round((x_max - x_min) / math.sqrt(aspect / density))))
        ny = max(1, int(round((y_max - y_min) * math.sqrt(aspect * density))))
        cx, cy = (x_max - x_min) / nx, (y_max - y_min) / ny
        I, J = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
        n = nx * ny
        pos = np.empty((n, 2))
        pos[:, 0] = x_min + cx * (I.ravel() + rng.uniform(0.0, 1.0, n))
        pos[:, 1] = y_min + cy * (J.ravel() + rng.uniform(0.0, 1.0, n))
    elif placement == "poisson":
        n = int(round(density * (x_max - x_min) * (y_max - y_min)))
        pos = np.empty((n, 2))
        pos[:, 0] = rng.uniform(x_min, x_max, n)
        pos[:, 1] = rng.uniform(y_min, y_max, n)
    else:
        raise ValueError(f"unknown scatterer placement {placement!r}: expected 'stratified' or 'poisson'")
    amp = rng.standard_normal(n)
    if inclusion_radius_mm is not None:
        r = positive("inclusion_radius_mm", inclusion_radius_mm)
        inside = ((pos[:, 0] - inclusion_center[0]) ** 2 + (pos[:, 1] - inclusion_center[1]) ** 2) < r * r
        amp[inside] *= factor
    return Scatterers(pos, amp)


def _taps(coord: np.ndarray, n: int, half_support: int):
    """Indices (N, 2K) of the 2K samples within K of fractional index ``coord`` and a validity mask."""
    start = np.floor(coord).astype(np.int64) - half_support + 1
    idx = start[:, None] + np.arange(2 * half_support, dtype=np.int64)[None, :]
    valid = (idx >= 0) & (idx < n)
    return idx, valid


def render_rf(positions, amplitudes, grid: ImagingGrid, psf: PSF | None = None) -> np.ndarray:
    """Noise-free RF image of point scatterers, each at its exact (sub-pixel) position.

    Parameters
    ----------
    positions : (N, 2) float, mm
        Scatterer positions [x, y] (axial, lateral).
    amplitudes : (N,) float
        Scatterer amplitudes.
    grid : ImagingGrid
        Pixel grid of the image.
    psf : PSF, optional
        Point spread function (paper's by default).

    Returns
    -------
    (n_axial, n_lateral) float64 RF image, ``RF[i, j] = sum_s a_s h_ax(x_i - x_s) h_lat(y_j - y_s)`` over the
    truncated PSF support.
    """
    psf = PSF() if psf is None else psf
    pos = np.asarray(positions, dtype=float)
    amp = np.asarray(amplitudes, dtype=float)
    if pos.ndim != 2 or pos.shape[1] != 2 or amp.shape != (pos.shape[0],):
        raise ValueError(f"positions must be (N, 2) and amplitudes (N,), got {pos.shape} and {amp.shape}")
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(amp))):
        raise ValueError("scatterer positions and amplitudes must be finite")
    hx_mm, hy_mm = psf.half_support_mm()
    kx = max(1, int(math.ceil(hx_mm / grid.dx)))
    ky = max(1, int(math.ceil(hy_mm / grid.dy)))
    fx = (pos[:, 0] - grid.x0) / grid.dx  # fractional pixel indices
    fy = (pos[:, 1] - grid.y0) / grid.dy
    # Only scatterers whose support reaches the image matter.
    keep = (fx > -kx) & (fx < grid.n_axial - 1 + kx) & (fy > -ky) & (fy < grid.n_lateral - 1 + ky)
    fx, fy, amp = fx[keep], fy[keep], amp[keep]
    n = len(amp)
    if n == 0:
        return np.zeros(grid.shape)
    ix, vx = _taps(fx, grid.n_axial, kx)
    iy, vy = _taps(fy, grid.n_lateral, ky)
    ax = psf.axial((ix - fx[:, None]) * grid.dx) * amp[:, None]
    ax[~vx] = 0.0
    ix[~vx] = 0
    lat = psf.lateral((iy - fy[:, None]) * grid.dy)
    lat[~vy] = 0.0
    iy[~vy] = 0
    # A: (n_axial, N) stored by column (scatterer); L: (N, n_lateral) stored by row.
    A = sp.csc_matrix((ax.ravel(), ix.ravel(), np.arange(0, n * 2 * kx + 1, 2 * kx)), shape=(grid.n_axial, n))
    L = sp.csr_matrix((lat.ravel(), iy.ravel(), np.arange(0, n * 2 * ky + 1, 2 * ky)), shape=(n, grid.n_lateral))
    return (A.tocsr() @ L).toarray()


def render_elevation_loop(motion, positions, amplitudes, elevation, plane_mm, sigma_elev_mm: float,
                          grid: ImagingGrid, psf: PSF, gain, snr_db: float, noise_seed: int = 11) -> np.ndarray:
    """The frames (n_frames, n_axial, n_lateral) float32 of a loop whose scatterers move in plane and the imaging
    plane out of it: frame ``k`` renders ``motion(k, positions)`` ((n, 2) mm) with amplitudes weighted by a
    Gaussian elevational beam of ``sigma_elev_mm`` centred on ``plane_mm[k]`` (``elevation``: each scatterer's
    elevational position, mm), times the depth ``gain`` ((n_axial,) per row), plus receiver noise at ``snr_db``
    of frame 0's clean power (seeded ``noise_seed``; the same sigma for every frame)."""
    frames = np.empty((len(plane_mm),) + tuple(grid.shape), np.float32)
    sigma = 0.0
    rng = np.random.default_rng(noise_seed)
    for k in range(len(plane_mm)):
        w = np.exp(-0.5 * ((elevation - plane_mm[k]) / sigma_elev_mm) ** 2)
        keep = w > 1e-3
        clean = render_rf(motion(k, positions[keep]), amplitudes[keep] * w[keep], grid, psf)
        if k == 0:
            sigma = noise_sigma(float(np.mean(clean ** 2)), snr_db)
        frames[k] = clean * np.asarray(gain)[:, None] + sigma * rng.standard_normal(clean.shape)
    return frames


def noise_sigma(signal_power: float, snr_db: float) -> float:
    """Noise standard deviation for ``SNR = 10 log10(signal_power / sigma^2)`` dB."""
    snr = float(snr_db)
    if not math.isfinite(snr):
        raise ValueError(f"snr_db must be finite (use None for no noise), got {snr_db!r}")
    p = float(signal_power)
    if not math.isfinite(p) or p < 0:
        raise ValueError(f"signal power must be finite and >= 0, got {signal_power!r}")
    return math.sqrt(p / 10.0 ** (snr / 10.0))


def add_noise(rf, snr_db: float, rng: np.random.Generator, *, signal_power: float | None = None) -> np.ndarray:
    """``rf`` plus white Gaussian noise at ``snr_db``.

    SNR definition: ``SNR = 10 log10(P_s / sigma_n^2)`` with ``P_s`` the mean square of the noise-free RF over
    the whole frame (``signal_power``; by default that of ``rf`` itself) and ``sigma_n^2`` the variance of the
    i.i.d. zero-mean Gaussian noise added to every sample.
    """
    rf = np.asarray(rf, dtype=float)
    p = float(np.mean(rf**2)) if signal_power is None else signal_power
    return rf + noise_sigma(p, snr_db) * rng.standard_normal(rf.shape)


def measured_snr_db(clean, noisy) -> float:
    """``10 log10(mean(clean^2) / mean((noisy - clean)^2))``, the SNR of :func:`add_noise`, measured."""
    clean = np.asarray(clean, dtype=float)
    noise = np.asarray(noisy, dtype=float) - clean
    return 10.0 * math.log10(float(np.mean(clean**2)) / float(np.mean(noise**2)))

