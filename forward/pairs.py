"""Simulated RF image pairs and short sequences for any linear-array probe and any displacement field, with exact
truth.

A pair is rendered with the PSF simulator of :mod:`forward.ultrasound`: point scatterers ``X`` with Gaussian
amplitudes make the reference, the *same* scatterers moved to ``X + u(X)`` make the moving frame, so the true
displacement at every scatterer is ``u(X)`` exactly (no image interpolation is involved) and
``reference(x) ~ moving(x + u(x))`` holds up to speckle decorrelation and noise.  Fields are callables or the
objects of :mod:`forward.fields` (compression, shear + rotation, bending, FE inclusions).

Probes (:class:`Probe`): centre frequency ``f0`` (3-15 MHz), axial sampling ``fs`` (20-80 MHz -> axial pixel
``c / (2 fs)``), line pitch (lateral pixel, 0.05-0.5 mm), lateral beam width (FWHM of the amplitude profile) and
pulse length in carrier cycles (-6 dB envelope duration ``cycles / f0``; the paper's 0.43 us at 5.5 MHz is 2.37
cycles).  The scatterer density follows the resolution cell, ``scatterers_per_cell / (sigma_x sigma_y)``, so every
probe sees fully developed speckle (the paper's 30 per mm^2 for its PSF).

Public API: :class:`Probe`, :data:`PROBES`, :func:`make_pair` -> :class:`Pair`, :func:`make_sequence` ->
:class:`SequencePair`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field as dc_field

import numpy as np

from .ultrasound import PSF, ImagingGrid, make_scatterers, noise_sigma, positive, render_rf

__all__ = ["Probe", "PROBES", "as_probe", "Pair", "SequencePair", "make_pair", "make_sequence", "FunctionField",
           "attenuation_gain_db", "alpha_for_floor", "noise_floor_depth", "box_points", "total_strain_error"]

#: Scatterers per (sigma_x * sigma_y) mm^2 of the PSF: 30 per mm^2 x 0.1406 mm x 0.5945 mm, the paper's density.
SCATTERERS_PER_CELL = 30.0 * 0.14060 * 0.59451


@dataclass(frozen=True)
class Probe:
    """A linear-array probe and its RF sampling.

    Parameters
    ----------
    f0_mhz : float
        Centre frequency, MHz (3-15 typical).
    fs_mhz : float
        Axial (RF) sampling frequency, MHz; must exceed ``2 f0`` (Nyquist of the carrier).  Axial pixel
        ``c / (2 fs)`` mm.
    pitch_mm : float
        Distance between RF lines (lateral pixel), mm.
    beam_fwhm_mm : float
        Lateral -6 dB width of the beam (amplitude), mm.
    cycles : float
        -6 dB duration of the pulse envelope in carrier cycles (paper: 0.43 us x 5.5 MHz = 2.37).
    name : str
    c_m_s : float
        Speed of sound, m/s.
    """

    f0_mhz: float = 5.5
    fs_mhz: float = 40.0
    pitch_mm: float = 0.3
    beam_fwhm_mm: float = 1.4
    cycles: float = 2.365
    name: str = "paper"
    c_m_s: float = 1540.0

    def __post_init__(self):
        for k in ("f0_mhz", "fs_mhz", "pitch_mm", "beam_fwhm_mm", "cycles", "c_m_s"):
            object.__setattr__(self, k, positive(f"probe {k}", getattr(self, k)))
        if self.fs_mhz <= 2.0 * self.f0_mhz:
            raise ValueError(f"probe sampling fs = {self.fs_mhz:g} MHz must exceed twice the centre frequency "
                             f"f0 = {self.f0_mhz:g} MHz")

    @property
    def c_mm_s(self) -> float:
        return self.c_m_s * 1e3

    @property
    def spacing(self) -> tuple[float, float]:
        """(axial, lateral) pixel spacing, mm."""
        return (self.c_mm_s / (2.0 * self.fs_mhz * 1e6), self.pitch_mm)

    @property
    def rf_period_mm(self) -> float:
        """Period of the RF carrier in depth, ``c / (2 f0)`` mm: the size of a peak hop."""
        return self.c_mm_s / (2.0 * self.f0_mhz * 1e6)

    @property
    def wavelength_mm(self) -> float:
        """Acoustic wavelength ``c / f0``, mm."""
        return self.c_mm_s / (self.f0_mhz * 1e6)

    def psf(self) -> PSF:
        """The separable PSF of :mod:`forward.ultrasound` for this probe."""
        return PSF(center_frequency_hz=self.f0_mhz * 1e6, pulse_length_s=self.cycles / (self.f0_mhz * 1e6),
                   lateral_fwhm_mm=self.beam_fwhm_mm, speed_of_sound_mm_per_s=self.c_mm_s)

    def density_per_mm2(self, scatterers_per_cell: float = SCATTERERS_PER_CELL) -> float:
        """Scatterer density giving ``scatterers_per_cell`` per ``sigma_x sigma_y`` of the PSF, per mm^2."""
        p = self.psf()
        return float(scatterers_per_cell) / (p.sigma_axial_mm * p.sigma_lateral_mm)

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("name", "f0_mhz", "fs_mhz", "pitch_mm", "beam_fwhm_mm", "cycles",
                                              "c_m_s")}


#: Probe presets spanning what users meet: the paper's, a low-frequency (abdominal) array with coarse lines, and
#: three linear arrays up to a 15 MHz high-frequency probe with 0.05 mm pitch.
PROBES = {
    "paper": Probe(5.5, 40.0, 0.3, 1.4, name="paper"),
    "L3": Probe(3.0, 20.0, 0.5, 2.5, name="L3"),
    "L7": Probe(7.5, 40.0, 0.2, 0.9, name="L7"),
    "L12": Probe(12.0, 60.0, 0.1, 0.5, name="L12"),
    "L15": Probe(15.0, 80.0, 0.05, 0.3, name="L15"),
}


def as_probe(spec) -> Probe:
    """A :class:`Probe` from a preset name, a Probe, or a dict of its parameters."""
    if isinstance(spec, Probe):
        return spec
    if isinstance(spec, str):
        if spec not in PROBES:
            raise ValueError(f"unknown probe preset {spec!r}: expected one of {tuple(PROBES)}")
        return PROBES[spec]
    if isinstance(spec, dict):
        return Probe(**spec)
    raise ValueError(f"probe must be a preset name, a Probe or a dict, got {type(spec).__name__}")


class FunctionField:
    """A plain callable ``u(points (n, 2) mm) -> (n, 2) mm`` as a field; strain by central differences (step
    ``h`` mm: truncation error ``O(h^2 |grad^3 u|)``, i.e. exact for fields up to quadratic)."""

    def __init__(self, fn, name: str = "custom", h: float = 1e-3):
        self.fn, self.name, self.h = fn, str(name), float(h)
        self.level = float("nan")

    def displacement(self, points) -> np.ndarray:
        p = np.asarray(points, float)
        u = np.asarray(self.fn(p), float)
        if u.shape != p.shape:
            raise ValueError(f"displacement callable must return shape {p.shape}, got {u.shape}")
        return u

    def strain(self, points) -> np.ndarray:
        p = np.asarray(points, float)
        h = self.h
        gx = (self.displacement(p + [h, 0]) - self.displacement(p - [h, 0])) / (2 * h)
        gy = (self.displacement(p + [0, h]) - self.displacement(p - [0, h])) / (2 * h)
        return np.column_stack([gx[:, 0], gy[:, 1], 0.5 * (gy[:, 0] + gx[:, 1])])


def _as_field(f):
    if callable(getattr(f, "displacement", None)) and callable(getattr(f, "strain", None)):
        return f
    if callable(f):
        return FunctionField(f)
    raise ValueError("field must be a callable points (n, 2) -> (n, 2) mm or have displacement() and strain()")


def _check_size(size_mm) -> tuple[float, float]:
    try:
        d, w = (float(s) for s in size_mm)
    except (TypeError, ValueError):
        raise ValueError(f"size_mm must be (depth, width) mm, got {size_mm!r}") from None
    if not (math.isfinite(d) and math.isfinite(w) and d > 0 and w > 0):
        raise ValueError(f"size_mm must be positive (depth, width) mm, got {size_mm!r}")
    return d, w


def _grid(pr: Probe, size_mm, top_mm: float) -> ImagingGrid:
    depth, width = _check_size(size_mm)
    if not (math.isfinite(float(top_mm)) and float(top_mm) >= 0):
        raise ValueError(f"top_mm must be >= 0 (depth of the first sample), got {top_mm!r}")
    return ImagingGrid.centred(depth_mm=depth, width_mm=width, spacing=pr.spacing, top_mm=float(top_mm))


def _scatterers(fields, grid: ImagingGrid, pr: Probe, rng, scatterers_per_cell):
    """Scatterers over the imaged area plus the margin any of ``fields`` moves tissue across plus the PSF
    support; amplitudes doubled inside a field's ``inside`` region (echogenic inclusion, as the paper)."""
    x0, x1, y0, y1 = grid.extent()
    psf = pr.psf()
    hx, hy = psf.half_support_mm()
    gx = np.linspace(max(0.0, x0 - hx), x1 + hx, 41)
    gy = np.linspace(y0 - hy, y1 + hy, 41)
    P = np.column_stack([a.ravel() for a in np.meshgrid(gx, gy, indexing="ij")])
    umax = np.zeros(2)
    for f in fields:
        u = f.displacement(P)
        if not np.all(np.isfinite(u)):
            raise ValueError(f"field {getattr(f, 'name', f)!r} is not finite over the imaged area")
        umax = np.maximum(umax, np.max(np.abs(u), axis=0))
    mx, my = umax + np.array([hx, hy]) + 0.5
    box = (max(0.0, x0 - mx), x1 + mx, y0 - my, y1 + my)   # tissue starts at the probe face x = 0
    scat = make_scatterers(rng, box, density_per_mm2=pr.density_per_mm2(scatterers_per_cell),
                           inclusion_radius_mm=None, cell_aspect=psf.sigma_axial_mm / psf.sigma_lateral_mm)
    for f in fields:
        inside = getattr(f, "inside", None)
        if callable(inside):
            scat.amplitudes[np.asarray(inside(scat.positions), bool)] *= 2.0
            break
    return scat, box


def _snr(snr_db):
    if snr_db is None:
        return None
    try:
        v = float(snr_db)
    except (TypeError, ValueError):
        v = float("nan")
    if not math.isfinite(v):
        raise ValueError(f"snr_db must be a finite number of dB or None (no noise), got {snr_db!r}")
    return v


def _seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or int(seed) < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


@dataclass
class Pair:
    """A simulated RF pair with its exact true motion.

    Attributes
    ----------
    ref, mov : (n_axial, n_lateral) float64
        Reference and moving RF frames; ``ref(x) ~ mov(x + u(x))``.
    spacing, origin : (2,) tuple, mm
        Pixel spacing and centre of pixel [0, 0] (``femreg.register(ref, mov, spacing=..., origin=...)``).
    field : the displacement field; probe : Probe; snr_db, seed, name; params : dict (JSON-serialisable).
    """

    ref: np.ndarray
    mov: np.ndarray
    spacing: tuple
    origin: tuple
    field: object
    probe: Probe
    snr_db: float | None
    seed: int
    name: str = ""
    params: dict = dc_field(default_factory=dict)

    def true_displacement(self, points) -> np.ndarray:
        """Exact ``u`` at reference-frame ``points`` (n, 2) mm -> (n, 2) mm."""
        return np.asarray(self.field.displacement(np.asarray(points, float)), float)

    def true_strain(self, points) -> np.ndarray:
        """Exact small strain ``[e_xx, e_yy, e_xy]`` at ``points`` (n, 2) mm -> (n, 3)."""
        return np.asarray(self.field.strain(np.asarray(points, float)), float)

    @property
    def grid(self) -> ImagingGrid:
        return ImagingGrid(*self.ref.shape, *self.spacing, *self.origin)

    def truth_on_grid(self, step=(1, 1)) -> dict:
        """``ux, uy, exx, eyy, exy`` on every ``step``-th pixel centre, each (n_axial', n_lateral'), plus the
        axes ``x`` and ``y`` (mm)."""
        g = self.grid
        x, y = g.x[::step[0]], g.y[::step[1]]
        P = np.column_stack([a.ravel() for a in np.meshgrid(x, y, indexing="ij")])
        u, e = self.true_displacement(P), self.true_strain(P)
        sh = (len(x), len(y))
        return dict(x=x, y=y, ux=u[:, 0].reshape(sh), uy=u[:, 1].reshape(sh), exx=e[:, 0].reshape(sh),
                    eyy=e[:, 1].reshape(sh), exy=e[:, 2].reshape(sh))


@dataclass
class SequencePair:
    """``n_frames`` RF frames of the same scatterers under a field at growing levels; frame 0 undeformed.

    ``true_displacement(k, points)`` / ``true_strain(k, points)``: frame 0 -> frame ``k`` at frame-0 points,
    exact (``frames[0](x) ~ frames[k](x + u_k(x))``).
    """

    frames: np.ndarray
    spacing: tuple
    origin: tuple
    fields: list
    levels: np.ndarray
    probe: Probe
    snr_db: float | None
    seed: int
    name: str = ""

    def _k(self, k) -> int:
        if isinstance(k, bool) or int(k) != k or not 0 <= int(k) < len(self.fields):
            raise ValueError(f"frame index must be an integer in [0, {len(self.fields)}), got {k!r}")
        return int(k)

    def true_displacement(self, k, points) -> np.ndarray:
        return np.asarray(self.fields[self._k(k)].displacement(np.asarray(points, float)), float)

    def true_strain(self, k, points) -> np.ndarray:
        return np.asarray(self.fields[self._k(k)].strain(np.asarray(points, float)), float)


def _render_frames(fields, pr: Probe, size_mm, snr_db, seed, top_mm, scatterers_per_cell, echo_gain_db=None,
                   tgc_db=None):
    grid = _grid(pr, size_mm, top_mm)
    gain = _echo_gain(echo_gain_db, grid)
    tgc = _echo_gain(tgc_db, grid, "tgc_db")
    snr_db = _snr(snr_db)
    ss_scat, ss_noise = np.random.SeedSequence(_seed(seed)).spawn(2)
    scat, box = _scatterers(fields, grid, pr, np.random.default_rng(ss_scat), scatterers_per_cell)
    psf = pr.psf()
    noise_rngs = [np.random.default_rng(s) for s in ss_noise.spawn(len(fields))]
    frames, sigma = [], 0.0
    for k, f in enumerate(fields):
        u = np.asarray(f.displacement(scat.positions), float)
        if not np.all(np.isfinite(u)):
            raise ValueError(f"field {getattr(f, 'name', f)!r} is not finite at the scatterers")
        clean = render_rf(scat.positions + u, scat.amplitudes, grid, psf)
        if k == 0 and snr_db is not None:
            sigma = noise_sigma(float(np.mean(clean**2)), snr_db)   # same noise level in every frame
        if gain is not None:        # after the noise level: snr_db stays the SNR at 0 dB gain
            clean *= gain[:, None]
        frames.append(clean + sigma * noise_rngs[k].standard_normal(clean.shape) if sigma > 0 else clean)
        if tgc is not None:         # the receiver's gain: echo and noise alike
            frames[-1] = frames[-1] * tgc[:, None]
    params = dict(probe=pr.to_dict(), size_mm=list(_check_size(size_mm)), top_mm=float(top_mm), snr_db=snr_db,
                  seed=int(seed), n_scatterers=len(scat), scatterer_box_mm=list(box), noise_sigma=sigma,
                  density_per_mm2=pr.density_per_mm2(scatterers_per_cell), shape=list(grid.shape))
    for key, g in (("echo_gain_db", gain), ("tgc_db", tgc)):
        if g is not None:
            params[key] = [float(v) for v in 20.0 * np.log10(g)]
    return frames, grid, params


def _echo_gain(gain_db, grid: ImagingGrid, name="echo_gain_db"):
    """Amplitude factor per row (n_axial,) of a depth-dependent gain in dB (callable of depth in mm), or None."""
    if gain_db is None:
        return None
    if not callable(gain_db):
        raise ValueError(f"{name} must be a callable of depth (mm) returning dB, got {gain_db!r}")
    g = np.broadcast_to(np.asarray(gain_db(grid.x), float), grid.x.shape)
    if not np.all(np.isfinite(g)):
        raise ValueError(f"{name} returned non-finite values")
    return 10.0 ** (g / 20.0)


def attenuation_gain_db(alpha_db_cm_mhz: float, f0_mhz: float):
    """Echo gain of round-trip attenuation ``alpha`` (dB / (cm MHz)) at ``f0``, as a callable of depth x (mm):
    ``-2 alpha f0 x / 10`` dB.  With the noise added after it (:func:`make_pair`, ``echo_gain_db``), the echo sinks
    to the noise floor at :func:`noise_floor_depth`; a time-gain compensation (``tgc_db``) lifts both."""
    slope = 2.0 * positive("alpha_db_cm_mhz", alpha_db_cm_mhz) * positive("f0_mhz", f0_mhz) / 10.0
    return lambda x: -slope * np.asarray(x, float)


def alpha_for_floor(depth_mm: float, snr_db: float, f0_mhz: float) -> float:
    """Attenuation (dB / (cm MHz), no TGC) that makes the echo of SNR ``snr_db`` at the probe face equal to the
    noise at ``depth_mm`` (the inverse of :func:`noise_floor_depth`)."""
    return float(snr_db) * 10.0 / (2.0 * positive("f0_mhz", f0_mhz) * positive("depth_mm", depth_mm))


def noise_floor_depth(snr_db: float, echo_gain_db, depths_mm) -> float:
    """First of ``depths_mm`` where the echo SNR ``snr_db + echo_gain_db(x)`` falls to 0 dB (echo power = noise
    power), or inf where it never does."""
    x = np.asarray(depths_mm, float)
    k = np.flatnonzero(float(snr_db) + np.asarray(echo_gain_db(x), float) <= 0.0)
    return float(x[k[0]]) if k.size else float("inf")


def make_pair(field, probe="paper", size_mm=(40.0, 30.0), snr_db: float | None = 30.0, seed: int = 0, *,
              top_mm: float = 2.0, scatterers_per_cell: float = SCATTERERS_PER_CELL, name: str = "",
              echo_gain_db=None, tgc_db=None) -> Pair:
    """Render a reference/moving RF pair related by ``field``.

    Parameters
    ----------
    field : object with ``displacement(points)`` and ``strain(points)`` (:mod:`forward.fields`), or a callable
        ``u(points (n, 2) mm) -> (n, 2) mm`` (strain then by central differences).
    probe : Probe, preset name (:data:`PROBES`) or dict
    size_mm : (depth, width) mm
        Imaged area, ``depth`` from ``top_mm`` down, ``width`` centred on ``y = 0``.
    snr_db : float or None
        ``10 log10(P_s / sigma_n^2)``, ``P_s`` the mean square of the noise-free reference; independent noise of the
        same ``sigma_n`` in both frames.  None: no noise.
    seed : int
        Seeds scatterers and noise (``numpy.random.SeedSequence``): the same arguments give identical frames.
    top_mm : float
        Depth of the first sample below the probe face, mm.
    echo_gain_db : callable(depth mm) -> dB, optional
        Depth-dependent gain of the echo in every frame, applied before the noise (whose level ``snr_db`` sets at
        0 dB gain): e.g. :func:`attenuation_gain_db` without time-gain compensation, so that the echo sinks to a
        noise floor below :func:`noise_floor_depth`.
    tgc_db : callable(depth mm) -> dB, optional
        Time-gain compensation: a depth-dependent gain of the frames after the noise (echo and noise alike; the
        SNR at each depth stays that of ``echo_gain_db``).

    Returns
    -------
    Pair
    """
    pr = as_probe(probe)
    f = _as_field(field)
    zero = _ZeroField()
    frames, grid, params = _render_frames([zero, f], pr, size_mm, snr_db, seed, top_mm, scatterers_per_cell,
                                          echo_gain_db, tgc_db)
    params["field"] = getattr(f, "name", "custom")
    return Pair(ref=frames[0], mov=frames[1], spacing=grid.spacing, origin=grid.origin, field=f, probe=pr,
                snr_db=params["snr_db"], seed=int(seed), name=name or params["field"], params=params)


def make_sequence(field, probe="paper", size_mm=(40.0, 30.0), snr_db: float | None = 30.0, seed: int = 0, *,
                  n_frames: int = 10, step: float = 0.01, top_mm: float = 2.0,
                  scatterers_per_cell: float = SCATTERERS_PER_CELL, name: str = "",
                  echo_gain_db=None, tgc_db=None) -> SequencePair:
    """``n_frames`` frames of the same scatterers under ``field.at(k * step)``, k = 0 .. n_frames - 1 (default
    10 frames at 1 % per frame: 9 % between the first and the last).  ``field`` needs an ``at(level)`` method
    (all fields of :mod:`forward.fields`); ``echo_gain_db`` and ``tgc_db`` as in :func:`make_pair`."""
    if not callable(getattr(field, "at", None)):
        raise ValueError("make_sequence needs a field with an at(level) method (forward.fields)")
    if isinstance(n_frames, bool) or int(n_frames) != n_frames or int(n_frames) < 2:
        raise ValueError(f"n_frames must be an integer >= 2, got {n_frames!r}")
    levels = float(step) * np.arange(int(n_frames))
    fields = [field.at(lv) for lv in levels]
    pr = as_probe(probe)
    frames, grid, params = _render_frames(fields, pr, size_mm, snr_db, seed, top_mm, scatterers_per_cell,
                                          echo_gain_db, tgc_db)
    return SequencePair(frames=np.stack(frames), spacing=grid.spacing, origin=grid.origin, fields=fields,
                        levels=levels, probe=pr, snr_db=params["snr_db"], seed=int(seed),
                        name=name or f"sequence {getattr(field, 'name', '')}")


class _ZeroField:
    name = "zero"
    level = 0.0

    def displacement(self, points):
        return np.zeros_like(np.asarray(points, float))

    def strain(self, points):
        return np.zeros((len(points), 3))


def box_points(shape, spacing, origin, box, step: int = 2) -> np.ndarray:
    """The pixel centres of a (n_axial, n_lateral) ``shape`` grid (``spacing``, ``origin`` mm) inside ``box``
    (x0, x1, y0, y1) mm, every ``step``-th row: (n, 2) mm."""
    x0, x1, y0, y1 = box
    x = origin[0] + np.arange(shape[0]) * spacing[0]
    y = origin[1] + np.arange(shape[1]) * spacing[1]
    X, Y = np.meshgrid(x[(x >= x0) & (x <= x1)][::step], y[(y >= y0) & (y <= y1)], indexing="ij")
    return np.column_stack([X.ravel(), Y.ravel()])


def total_strain_error(estimate, truth) -> float:
    """Total strain error (%) of (n, 3) [e_xx, e_yy, e_xy] against the truth: relative L2, e_xy weighted 2."""
    w = np.array([1.0, 1.0, 2.0])
    est, e = np.asarray(estimate, float), np.asarray(truth, float)
    return 100.0 * float(np.sqrt(np.sum(w * (est - e) ** 2) / np.sum(w * e ** 2)))



def elevation_scatterers(probe, box, sigma_elev_mm: float, elevation_max_mm: float, seed: int = 7):
    """``(positions (n, 2) mm, elevation (n,) mm, amplitudes (n,))`` of a scatterer slab for a loop whose imaging
    plane moves from 0 to ``elevation_max_mm`` out of plane under a Gaussian elevational beam of ``sigma_elev_mm``
    (:func:`forward.ultrasound.render_elevation_loop`): 3 sigma beyond either end, as dense as the in-plane speckle
    of :data:`SCATTERERS_PER_CELL` per resolution cell of ``probe`` (:class:`Probe`); ``box`` the in-plane extent
    (x0, x1, y0, y1) mm."""
    psf = probe.psf()
    zlo, zhi = -3 * sigma_elev_mm, elevation_max_mm + 3 * sigma_elev_mm
    rng = np.random.default_rng(seed)
    dens = probe.density_per_mm2(SCATTERERS_PER_CELL) * (zhi - zlo) / (math.sqrt(2 * math.pi) * sigma_elev_mm)
    scat = make_scatterers(rng, box, density_per_mm2=dens, inclusion_radius_mm=None,
                           cell_aspect=psf.sigma_axial_mm / psf.sigma_lateral_mm)
    return scat.positions, rng.uniform(zlo, zhi, len(scat.positions)), scat.amplitudes.copy()
