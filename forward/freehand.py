"""Simulated freehand cine loops: a hand-held probe pressing and releasing over tissue with an inclusion, with
pauses, the probe sliding, out-of-plane drift and gain steps, and the exact motion between any two frames.

Model
-----
Tissue points ``X = (x, y, z)`` (depth, lateral, elevation; mm) carry point scatterers.  Pressing with the probe
deforms the imaging plane by ``X -> X + c U(X)`` with ``c`` the compression level (fraction) of the frame and
``U`` the displacement per unit compression of :class:`FreehandTissue` (uniform compression towards the probe
face, lateral expansion, and a Gaussian stiff or soft inclusion).  The probe slides laterally by ``p`` and
elevationally by ``e`` over the tissue; a scatterer at elevation ``z`` is seen with the weight
``exp(-(z - e)**2 / (2 sigma_e**2))`` of the elevational beam profile, so elevational motion decorrelates the
speckle as in a real array.  Frame ``k`` is then the PSF image (:func:`forward.ultrasound.render_rf`) of the
scatterers at ``X + c_k U(X) - (0, p_k)`` times the frame's gain.

Truth: for two frames ``i, j`` and a point ``x`` of frame ``i``, ``X`` solves ``X + c_i U(X) - (0, p_i) = x``
(fixed point), ``u(x) = (c_j - c_i) U(X) - (0, p_j - p_i)`` and the strain is ``(c_j - c_i) grad U (I + c_i
grad U)^-1`` (:meth:`FreehandLoop.true_displacement`, :meth:`FreehandLoop.true_strain`).

Public API: :class:`FreehandMotion`, :class:`FreehandTissue`, :func:`simulate_freehand` -> :class:`FreehandLoop`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field as dc_field

import numpy as np

from .pairs import SCATTERERS_PER_CELL, _grid, _seed, _snr, as_probe
from .ultrasound import make_scatterers, noise_sigma, render_rf

__all__ = ["FreehandMotion", "FreehandTissue", "FreehandLoop", "simulate_freehand"]


@dataclass(frozen=True)
class FreehandTissue:
    """Displacement per unit compression ``U`` (mm per unit level) of the imaged plane.

    ``U_x = -(x + beta (x - x_c) g)``, ``U_y = (y - y_c) / 2`` with ``g = exp(-r**2 / (2 R**2))``, ``r`` the
    distance to the inclusion centre ``(x_c, y_c)`` (mm) and ``R`` its radius: uniform compression towards the probe
    face (``x = 0``) with incompressible lateral expansion, and a Gaussian bump that scales the axial strain at the
    centre by ``1 + beta`` (``beta < 0``: stiff inclusion, ``> 0``: soft).  Closed form, not a solution of
    elasticity; the strain ``e_xx = -(1 + beta g (1 - (x - x_c)**2 / R**2))`` is exact for this ``U``."""

    inclusion_depth_mm: float = 8.0
    inclusion_lateral_mm: float = 0.0
    inclusion_radius_mm: float = 2.5
    beta: float = -0.5

    def U(self, points) -> np.ndarray:
        p = np.asarray(points, float)
        dx, dy = p[:, 0] - self.inclusion_depth_mm, p[:, 1] - self.inclusion_lateral_mm
        g = np.exp(-(dx ** 2 + dy ** 2) / (2.0 * self.inclusion_radius_mm ** 2))
        return np.column_stack([-(p[:, 0] + self.beta * dx * g), 0.5 * dy])

    def grad_U(self, points) -> np.ndarray:
        """(n, 2, 2): ``[[dUx/dx, dUx/dy], [dUy/dx, dUy/dy]]``."""
        p = np.asarray(points, float)
        R2 = self.inclusion_radius_mm ** 2
        dx, dy = p[:, 0] - self.inclusion_depth_mm, p[:, 1] - self.inclusion_lateral_mm
        g = np.exp(-(dx ** 2 + dy ** 2) / (2.0 * R2))
        G = np.zeros((len(p), 2, 2))
        G[:, 0, 0] = -(1.0 + self.beta * g * (1.0 - dx ** 2 / R2))
        G[:, 0, 1] = self.beta * dx * dy * g / R2
        G[:, 1, 1] = 0.5
        return G


@dataclass(frozen=True)
class FreehandMotion:
    """How the hand moves the probe, frame by frame.

    Parameters
    ----------
    n_frames : int
    frame_rate_hz : float
        Frames per second.
    press_hz : float
        Compress/release cycles per second (1-3 typical).
    amplitude : float
        Peak compression (fraction, 0-0.03): ``c(t) = amplitude (1 - cos(2 pi press_hz t')) / 2``, ``t'`` the time
        spent pressing (the phase stands still during pauses).
    pauses : sequence of (t0, t1) s
        Intervals in which the hand holds still.
    slide_mm_s : float
        Lateral sliding speed of the probe, mm/s (during pauses too).
    elevation_mm_s : float
        Out-of-plane drift speed, mm/s; ``elevation_jitter_mm`` adds a seeded random walk (standard deviation per
        frame, mm).
    gain_steps : sequence of (frame, factor)
        From ``frame`` on the frames are multiplied by ``factor`` (cumulative).
    """

    n_frames: int = 60
    frame_rate_hz: float = 30.0
    press_hz: float = 1.5
    amplitude: float = 0.02
    pauses: tuple = ()
    slide_mm_s: float = 0.3
    elevation_mm_s: float = 0.2
    elevation_jitter_mm: float = 0.01
    gain_steps: tuple = ()

    def __post_init__(self):
        if isinstance(self.n_frames, bool) or int(self.n_frames) != self.n_frames or self.n_frames < 2:
            raise ValueError(f"n_frames must be an integer >= 2, got {self.n_frames!r}")
        for name in ("frame_rate_hz", "press_hz"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0, got {v!r}")
        if not (math.isfinite(self.amplitude) and 0 <= self.amplitude < 0.2):
            raise ValueError(f"amplitude must be a compression fraction in [0, 0.2), got {self.amplitude!r}")
        for f, g in self.gain_steps:
            if not (g > 0 and math.isfinite(g)):
                raise ValueError(f"gain factors must be > 0, got {g!r} at frame {f}")

    def schedule(self, rng) -> dict:
        """Per frame: ``time`` s, ``compression`` (fraction), ``slide`` and ``elevation`` (mm), ``gain``."""
        n = int(self.n_frames)
        t = np.arange(n) / float(self.frame_rate_hz)
        moving = np.ones(n, bool)
        for t0, t1 in self.pauses:
            moving &= ~((t >= t0) & (t < t1))
        # the phase advances only while the hand presses
        tp = np.concatenate([[0.0], np.cumsum(moving[1:] / float(self.frame_rate_hz))])
        comp = self.amplitude * 0.5 * (1.0 - np.cos(2.0 * np.pi * self.press_hz * tp))
        slide = self.slide_mm_s * t
        elev = self.elevation_mm_s * t + np.concatenate(
            [[0.0], np.cumsum(rng.normal(0.0, self.elevation_jitter_mm, n - 1))])
        gain = np.ones(n)
        for f, g in self.gain_steps:
            gain[int(f):] *= float(g)
        return dict(time=t, compression=comp, slide=slide, elevation=elev, gain=gain)


@dataclass
class FreehandLoop:
    """A simulated cine loop with its exact motion.

    Attributes
    ----------
    frames : (n, n_axial, n_lateral) float64
        RF frames (gain applied).
    spacing, origin : (2,) mm
    time, compression, slide, elevation, gain : (n,) per-frame schedule (s, fraction, mm, mm, factor)
    tissue : FreehandTissue; motion : FreehandMotion; probe : forward.pairs.Probe
    """

    frames: np.ndarray
    spacing: tuple
    origin: tuple
    time: np.ndarray
    compression: np.ndarray
    slide: np.ndarray
    elevation: np.ndarray
    gain: np.ndarray
    tissue: FreehandTissue
    motion: FreehandMotion
    probe: object
    params: dict = dc_field(default_factory=dict)

    def _tissue_points(self, i, points):
        """Tissue points X (in-plane) imaged at ``points`` of frame ``i``: X + c_i U(X) - (0, p_i) = x."""
        x = np.asarray(points, float) + np.array([0.0, self.slide[i]])
        X = x.copy()
        for _ in range(30):                 # contraction: |c grad U| <~ 0.05
            X_new = x - self.compression[i] * self.tissue.U(X)
            if np.max(np.abs(X_new - X)) < 1e-12:
                X = X_new
                break
            X = X_new
        return X

    def true_displacement(self, i, j, points) -> np.ndarray:
        """Frame ``i`` -> frame ``j`` at frame-``i`` ``points`` (n, 2) mm: ``frames[i](x) ~ frames[j](x + u)``."""
        X = self._tissue_points(i, points)
        u = (self.compression[j] - self.compression[i]) * self.tissue.U(X)
        u[:, 1] -= self.slide[j] - self.slide[i]
        return u

    def true_strain(self, i, j, points) -> np.ndarray:
        """Small strain ``[e_xx, e_yy, e_xy]`` (n, 3) of frame ``i`` -> ``j`` at frame-``i`` points."""
        X = self._tissue_points(i, points)
        G = self.tissue.grad_U(X)
        F = np.eye(2)[None] + self.compression[i] * G
        D = (self.compression[j] - self.compression[i]) * G @ np.linalg.inv(F)
        return np.column_stack([D[:, 0, 0], D[:, 1, 1], 0.5 * (D[:, 0, 1] + D[:, 1, 0])])

    def strain_pattern(self, i, points) -> np.ndarray:
        """Axial strain per unit compression step at frame ``i``'s ``points``, (n,): what a normalised strain
        image of any pair from frame ``i`` shows once divided by its mean (to first order in the step)."""
        X = self._tissue_points(i, points)
        G = self.tissue.grad_U(X)
        D = G @ np.linalg.inv(np.eye(2)[None] + self.compression[i] * G)
        return D[:, 0, 0]

    def pixel_points(self) -> np.ndarray:
        n = self.frames.shape[1:]
        x = self.origin[0] + self.spacing[0] * np.arange(n[0])
        y = self.origin[1] + self.spacing[1] * np.arange(n[1])
        X, Y = np.meshgrid(x, y, indexing="ij")
        return np.column_stack([X.ravel(), Y.ravel()])


def simulate_freehand(motion: FreehandMotion | None = None, *, probe="L7", size_mm=(14.0, 12.0),
                      tissue: FreehandTissue | None = None, snr_db: float | None = 30.0, seed: int = 0,
                      top_mm: float = 1.0, elevation_sigma_mm: float = 0.5,
                      scatterers_per_cell: float = SCATTERERS_PER_CELL, dtype=np.float64) -> FreehandLoop:
    """Render a freehand cine loop (see the module docstring).

    Parameters
    ----------
    motion : FreehandMotion (default: 60 frames at 30 Hz, 1.5 Hz pressing to 2 %, 0.3 mm/s slide)
    probe : forward.pairs.Probe, preset name or dict (any linear array of :data:`forward.pairs.PROBES`)
    size_mm : (depth, width) mm of the image, ``depth`` from ``top_mm`` down, ``width`` centred on ``y = 0``
    tissue : FreehandTissue (default: stiff inclusion of 2.5 mm radius at 8 mm depth)
    snr_db : float or None; the same noise level (of the first frame, before gain) in every frame
    seed : int, seeds scatterers, elevation jitter and noise
    elevation_sigma_mm : float, standard deviation of the elevational beam profile (amplitude), mm
    dtype : output sample type (float64; float32 halves the memory of long loops)
    """
    motion = FreehandMotion() if motion is None else motion
    tissue = FreehandTissue() if tissue is None else tissue
    pr = as_probe(probe)
    grid = _grid(pr, size_mm, top_mm)
    snr_db = _snr(snr_db)
    ss_scat, ss_motion, ss_noise = np.random.SeedSequence(_seed(seed)).spawn(3)
    sch = motion.schedule(np.random.default_rng(ss_motion))
    psf = pr.psf()
    hx, hy = psf.half_support_mm()
    x0, x1, y0, y1 = grid.extent()
    cmax = float(np.max(sch["compression"]))
    mx = cmax * (x1 + abs(tissue.beta) * tissue.inclusion_radius_mm) + hx + 0.5
    my = 0.5 * cmax * max(abs(y0), abs(y1)) + hy + 0.5
    box = (max(0.0, x0 - mx), x1 + mx, y0 - my + min(0.0, sch["slide"].min()), y1 + my + max(0.0, sch["slide"].max()))
    zlo = float(sch["elevation"].min()) - 3.0 * elevation_sigma_mm
    zhi = float(sch["elevation"].max()) + 3.0 * elevation_sigma_mm
    rng = np.random.default_rng(ss_scat)
    # as many scatterers per effective beam thickness (sqrt(2 pi) sigma_e) as the 2D simulator puts per plane
    per_plane = pr.density_per_mm2(scatterers_per_cell)
    dens = per_plane * (zhi - zlo) / (math.sqrt(2.0 * math.pi) * elevation_sigma_mm)
    scat = make_scatterers(rng, box, density_per_mm2=dens, inclusion_radius_mm=None,
                           cell_aspect=psf.sigma_axial_mm / psf.sigma_lateral_mm)
    z = rng.uniform(zlo, zhi, len(scat))
    U = tissue.U(scat.positions)
    noise_rngs = [np.random.default_rng(s) for s in ss_noise.spawn(motion.n_frames)]
    frames = np.empty((motion.n_frames,) + grid.shape, dtype=dtype)
    sigma = 0.0
    for k in range(motion.n_frames):
        w = np.exp(-0.5 * ((z - sch["elevation"][k]) / elevation_sigma_mm) ** 2)
        keep = w > 1e-3
        pos = scat.positions[keep] + sch["compression"][k] * U[keep]
        pos[:, 1] -= sch["slide"][k]
        clean = render_rf(pos, scat.amplitudes[keep] * w[keep], grid, psf)
        if k == 0 and snr_db is not None:
            sigma = noise_sigma(float(np.mean(clean ** 2)), snr_db)
        if sigma > 0:
            clean = clean + sigma * noise_rngs[k].standard_normal(clean.shape)
        frames[k] = sch["gain"][k] * clean
    params = dict(probe=pr.to_dict(), size_mm=[float(s) for s in size_mm], top_mm=float(top_mm), snr_db=snr_db,
                  seed=int(seed), n_scatterers=len(scat), elevation_sigma_mm=float(elevation_sigma_mm),
                  noise_sigma=sigma)
    return FreehandLoop(frames=frames, spacing=grid.spacing, origin=grid.origin, time=sch["time"],
                        compression=sch["compression"], slide=sch["slide"], elevation=sch["elevation"],
                        gain=sch["gain"], tissue=tissue, motion=motion, probe=pr, params=params)
