"""Simulated RF pairs of convex and phased (sector) arrays, with exact truth, from the PSF renderer of
:mod:`forward.ultrasound` sampled along rays (no array simulator).

Point scatterers are drawn in physical space (x depth, y lateral, mm; tissue from the face plane x = 0 down) and
moved by the field there, exactly as for a linear pair (:mod:`forward.pairs`).  Each frame is rendered in beam
coordinates: a scatterer at physical (x, y) sits at range ``r`` (from the face along its ray) and angle
``theta`` of the geometry (:class:`femreg.geometry.Convex` / ``Sector`` conventions), and is rendered at
``(r, rho_c theta)`` on the (range, arc length at ``rho_c``) grid with the probe's separable PSF, ``rho_c`` the
apex distance of the middle sample.  So the pulse runs along the ray and the beam is a fixed angle wide (its
physical width grows in proportion to the distance from the apex, as a focused curved array's does away from the
focus), and sample ``[i, j]`` is the echo on ray ``j`` at range ``r_0 + i dr``.

Public API: :func:`make_beam_pair` -> :class:`BeamPair`; :func:`make_beam_sequence` -> :class:`BeamSequence`
(frames of a cine loop under one field at growing levels).
"""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field, replace

import numpy as np

from .pairs import SCATTERERS_PER_CELL, Pair, SequencePair, _as_field, _seed, _snr, _ZeroField, as_probe
from .ultrasound import ImagingGrid, make_scatterers, noise_sigma, render_rf

__all__ = ["BeamPair", "make_beam_pair", "BeamSequence", "make_beam_sequence"]


@dataclass
class BeamPair(Pair):
    """A simulated convex / sector pair: :class:`forward.pairs.Pair` whose frames are (n_samples, n_rays),
    ``spacing`` = (dr mm, dtheta deg), ``origin`` = (range of the first sample mm, 0) and ``geometry`` the
    mapping (``femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin,
    geometry=pair.geometry)``).  Truth in physical coordinates."""

    geometry: object = None

    def sample_points(self) -> np.ndarray:
        """Physical positions of the samples, (n_samples * n_rays, 2) mm, C order."""
        X, Y = self.geometry.sample_positions(self.ref.shape, self.spacing, self.origin)
        return np.column_stack([X.ravel(), Y.ravel()])


def _check_beam(geometry, n_rays):
    from femreg import Convex

    if not isinstance(geometry, Convex):      # femreg.Sector is a Convex with its apex on the face
        raise ValueError("make_beam_pair / make_beam_sequence need a femreg.Convex or femreg.Sector geometry; use "
                         "forward.pairs.make_pair / make_sequence for a linear array")
    n_rays = int(n_rays)
    if n_rays < 8:
        raise ValueError(f"n_rays must be >= 8, got {n_rays}")
    return n_rays


def _render_beam_frames(fields, geo, pr, depth_mm, n_rays, snr_db, seed, top_mm, scatterers_per_cell,
                        lines_per_beam):
    """One frame per field of ``fields`` (the first the reference, the last the largest motion), the same
    scatterers moved by each; returns ``(frames, probe, params)``.  The scatterer box covers the largest
    displacement of any field; the noise of frame k is the k-th child of the seed's noise stream."""
    dr = pr.spacing[0]
    n_s = max(8, int(round(float(depth_mm) / dr)))
    rho_c = geo.radius_mm + top_mm + 0.5 * (n_s - 1) * dr
    ds = rho_c * geo.pitch_rad
    grid = ImagingGrid(n_s, n_rays, dr, ds, float(top_mm), -0.5 * (n_rays - 1) * ds)
    if lines_per_beam is not None and pr.beam_fwhm_mm < float(lines_per_beam) * ds:
        pr = replace(pr, beam_fwhm_mm=float(lines_per_beam) * ds)
    psf = pr.psf()
    hx, hy = psf.half_support_mm()
    # physical box of the imaged sector + the PSF support (scaled to the widest radius) + the motion
    X, Y = geo.sample_positions((n_s, n_rays), (dr, geo.angle_pitch_deg), (top_mm, 0.0))
    P = np.column_stack([X.ravel()[::7], Y.ravel()[::7]])
    umax = np.max([np.nanmax(np.abs(f.displacement(P)), axis=0) for f in fields], axis=0)
    grow = (geo.radius_mm + top_mm + depth_mm) / rho_c
    m = umax + np.array([hx, hy * grow]) + 0.5
    box = (max(0.0, X.min() - m[0]), X.max() + m[0], Y.min() - m[1], Y.max() + m[1])
    ss_scat, ss_noise = np.random.SeedSequence(_seed(seed)).spawn(2)
    scat = make_scatterers(np.random.default_rng(ss_scat), box,
                           density_per_mm2=pr.density_per_mm2(scatterers_per_cell)
                           * min(3.0, rho_c / (geo.radius_mm + top_mm)),
                           inclusion_radius_mm=None, cell_aspect=psf.sigma_axial_mm / psf.sigma_lateral_mm)
    inside = getattr(fields[-1], "inside", None)
    if callable(inside):
        scat.amplitudes[np.asarray(inside(scat.positions), bool)] *= 2.0
    frames, sigma = [], 0.0
    noise_rngs = [np.random.default_rng(s) for s in ss_noise.spawn(len(fields))]
    for k, fk in enumerate(fields):
        u = np.asarray(fk.displacement(scat.positions), float)
        if not np.all(np.isfinite(u)):
            raise ValueError(f"field {getattr(fk, 'name', fk)!r} is not finite at the scatterers")
        q = scat.positions + u
        r, th = geo.to_beam(q[:, 0], q[:, 1])
        clean = render_rf(np.column_stack([r, rho_c * th]), scat.amplitudes, grid, psf)
        if k == 0 and snr_db is not None:
            sigma = noise_sigma(float(np.mean(clean**2)), snr_db)
        frames.append(clean + sigma * noise_rngs[k].standard_normal(clean.shape) if sigma > 0 else clean)
    params = dict(probe=pr.to_dict(), geometry=geo.to_dict(), depth_mm=float(depth_mm), n_rays=n_rays,
                  top_mm=float(top_mm), snr_db=snr_db, seed=int(seed), n_scatterers=len(scat),
                  scatterer_box_mm=[float(b) for b in box], noise_sigma=sigma, shape=[n_s, n_rays])
    return frames, pr, params


def make_beam_pair(field, geometry, probe="paper", depth_mm: float = 40.0, n_rays: int = 64,
                   snr_db: float | None = 30.0, seed: int = 0, *, top_mm: float = 3.0,
                   scatterers_per_cell: float = SCATTERERS_PER_CELL, lines_per_beam: float | None = 3.0,
                   name: str = "") -> BeamPair:
    """Render a reference/moving pair of a convex or sector probe related by ``field`` (physical, mm).

    ``geometry``: :class:`femreg.geometry.Convex` or ``Sector``; ``probe``: its pulse and axial sampling (the
    lateral beam width is taken at ``rho_c``); ``depth_mm`` of range from ``top_mm``; ``n_rays`` rays centred on
    angle 0.  ``lines_per_beam``: the beam's -6 dB width at ``rho_c`` is at least this many line spacings
    (``rho_c dtheta``; a scanner's line density samples its beam, as the paper probe's 1.4 mm beam and 0.3 mm
    lines, 4.7 per beam; a linear pair with 1.6 lines per beam has 3.7 % total strain error under 1 %
    compression, 0.2 % with 4.7); None: the probe's width as given.  Scatterers only at x >= 0 (the tissue
    under the face plane).  Noise, seeding: as
    :func:`forward.pairs.make_pair`."""
    n_rays = _check_beam(geometry, n_rays)
    f = _as_field(field)
    frames, pr, params = _render_beam_frames([_ZeroField(), f], geometry, as_probe(probe), depth_mm, n_rays,
                                             _snr(snr_db), seed, top_mm, scatterers_per_cell, lines_per_beam)
    params["field"] = getattr(f, "name", "custom")
    return BeamPair(ref=frames[0], mov=frames[1], spacing=(pr.spacing[0], float(geometry.angle_pitch_deg)),
                    origin=(float(top_mm), 0.0), field=f, probe=pr, snr_db=params["snr_db"], seed=int(seed),
                    name=name or params["field"], params=params, geometry=geometry)


@dataclass
class BeamSequence(SequencePair):
    """Frames of a convex / sector probe under one field at growing levels (:func:`make_beam_sequence`):
    :class:`forward.pairs.SequencePair` whose frames are (n_frames, n_samples, n_rays), ``spacing`` = (dr mm,
    dtheta deg), ``origin`` = (range of the first sample mm, 0) and ``geometry`` the mapping
    (``femreg.track(seq.frames, spacing=seq.spacing[0], origin=seq.origin, geometry=seq.geometry)``).
    ``true_displacement(k, points)`` / ``true_strain(k, points)``: frame 0 -> frame k at frame-0 physical points
    (x depth, y lateral, mm), exact."""

    geometry: object = None
    params: dict = dc_field(default_factory=dict)

    def sample_points(self) -> np.ndarray:
        """Physical positions of the samples, (n_samples * n_rays, 2) mm, C order."""
        X, Y = self.geometry.sample_positions(self.frames.shape[1:], self.spacing, self.origin)
        return np.column_stack([X.ravel(), Y.ravel()])


def make_beam_sequence(field, geometry, probe="paper", depth_mm: float = 40.0, n_rays: int = 64,
                       snr_db: float | None = 30.0, seed: int = 0, *, n_frames: int = 5, step: float = 0.005,
                       top_mm: float = 3.0, scatterers_per_cell: float = SCATTERERS_PER_CELL,
                       lines_per_beam: float | None = 3.0, name: str = "") -> BeamSequence:
    """``n_frames`` frames of a convex / sector probe, the same scatterers under ``field.at(k * step)``, k = 0 ..
    n_frames - 1 (default 5 frames at 0.5 % per frame).  ``field`` needs an ``at(level)`` method (all fields of
    :mod:`forward.fields`); the other arguments as in :func:`make_beam_pair`, whose renderer this is (the
    scatterer box covers the last frame's motion)."""
    if not callable(getattr(field, "at", None)):
        raise ValueError("make_beam_sequence needs a field with an at(level) method (forward.fields)")
    if isinstance(n_frames, bool) or int(n_frames) != n_frames or int(n_frames) < 2:
        raise ValueError(f"n_frames must be an integer >= 2, got {n_frames!r}")
    n_rays = _check_beam(geometry, n_rays)
    levels = float(step) * np.arange(int(n_frames))
    fields = [field.at(lv) for lv in levels]
    frames, pr, params = _render_beam_frames(fields, geometry, as_probe(probe), depth_mm, n_rays, _snr(snr_db),
                                             seed, top_mm, scatterers_per_cell, lines_per_beam)
    params["field"] = getattr(field, "name", "custom")
    return BeamSequence(frames=np.stack(frames), spacing=(pr.spacing[0], float(geometry.angle_pitch_deg)),
                        origin=(float(top_mm), 0.0), fields=fields, levels=levels, probe=pr,
                        snr_db=params["snr_db"], seed=int(seed), name=name or f"sequence {params['field']}",
                        geometry=geometry, params=params)
