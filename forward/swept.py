"""Simulated RF volume pairs of mechanically swept 3D probes (:class:`femreg.Swept`), with exact truth, from the
volume renderer of :mod:`forward.volume` sampled along fan frames.

Point scatterers are drawn in physical space (x depth, y lateral, z elevational, mm; tissue from the face plane
x = 0 down) and moved by the field there, exactly as for a Cartesian pair (:func:`forward.volume.make_volume_pair`).
Each volume is rendered in beam coordinates: a scatterer at physical (x, y, z) sits at range ``r``, line coordinate
``l`` and tilt ``phi`` of the geometry, and is rendered at ``(r, l, rho_e phi)`` (``l`` in mm for a linear array,
``rho_c theta`` for a curved one) on the (range, line, elevational arc at ``rho_e``) grid with the probe's separable
3D PSF (:func:`forward.volume.render_volume`); ``rho_c`` / ``rho_e`` are the apex / sweep-axis distances of the
middle sample of the central line.  So the pulse runs along the ray and the beams are a fixed angle wide (as
:mod:`forward.beam` for 2D frames), and sample ``[i, j, k]`` is the echo on line ``j`` of frame ``k`` at range
``r_0 + i dr``.

Public API: :func:`make_swept_pair` -> :class:`SweptPair`; :func:`make_swept_sequence` -> :class:`SweptSequence`
(frame 0 and one volume per frame-0 -> frame-k field, the same scatterers: a swept probe's volume sequence).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .volume import (ImagingVolume, VolumePair, VolumeSequence, _as_field3, _seed, _snr, _Zero, as_volume_probe,
                     make_scatterers_3d, render_volume)
from .ultrasound import noise_sigma

__all__ = ["SweptPair", "SweptSequence", "make_swept_pair", "make_swept_sequence"]


@dataclass
class SweptSequence(VolumeSequence):
    """A simulated swept volume sequence: :class:`forward.volume.VolumeSequence` whose volumes are (n_samples,
    n_lines, n_frames) on the fan, ``spacing`` = (dr mm, line pitch mm or deg, frame step deg), ``origin`` = (range
    of the first sample mm, first line y mm or 0, 0) and ``geometry`` the mapping
    (``femreg.track(seq.frames, spacing=seq.spacing, origin=seq.origin, geometry=seq.geometry)``); ``grid`` is the
    beam-coordinate grid it was rendered on.  Truth (``fields[k]``: frame 0 -> k) in physical coordinates."""

    geometry: object = None
    sample_spacing: tuple = ()
    sample_origin: tuple = ()

    @property
    def spacing(self):
        return self.sample_spacing

    @property
    def origin(self):
        return self.sample_origin

    def voxel_points(self) -> np.ndarray:
        """Physical positions of the samples, (n, 3) mm, C order of the volume."""
        X = self.geometry.sample_positions(self.frames.shape[1:], self.sample_spacing, self.sample_origin)
        return np.column_stack([c.ravel() for c in X])


@dataclass
class SweptPair(SweptSequence, VolumePair):
    """A simulated swept pair (:class:`SweptSequence` of two volumes): ``ref``, ``mov``, ``field``
    (``femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin, geometry=pair.geometry)``)."""


def make_swept_pair(field, geometry, probe="matrix7", depth_mm: float = 20.0, n_lines: int = 64,
                    n_frames: int = 31, *, top_mm: float = 2.0, snr_db: float | None = 30.0, seed: int = 0,
                    lines_per_beam: float | None = 3.0, density_factor_max: float = 3.0) -> SweptPair:
    """Render a reference / moving swept pair related by ``field`` (physical, mm; a callable (n, 3) -> (n, 3) or
    an object with ``displacement``): :func:`make_swept_sequence` of that one field."""
    seq = make_swept_sequence([field], geometry, probe, depth_mm, n_lines, n_frames, top_mm=top_mm, snr_db=snr_db,
                              seed=seed, lines_per_beam=lines_per_beam, density_factor_max=density_factor_max)
    seq.params["field"] = seq.params["field"][0]
    return SweptPair(**{k: getattr(seq, k) for k in ("frames", "grid", "fields", "params", "path", "geometry",
                                                     "sample_spacing", "sample_origin")})


def make_swept_sequence(fields, geometry, probe="matrix7", depth_mm: float = 20.0, n_lines: int = 64,
                        n_frames: int = 31, *, top_mm: float = 2.0, snr_db: float | None = 30.0, seed: int = 0,
                        lines_per_beam: float | None = 3.0, density_factor_max: float = 3.0) -> SweptSequence:
    """Render frame 0 (undeformed) and one swept volume per field in ``fields`` (each physical, mm, frame 0 ->
    frame k: a callable (n, 3) -> (n, 3) or an object with ``displacement``), the same scatterers in every volume.

    ``geometry``: :class:`femreg.Swept`; ``probe``: a :data:`forward.volume.VOLUME_PROBES` preset or a
    :class:`forward.volume.VolumeProbe` (its pulse, axial sampling, a linear array's line pitch ``pitch_mm``, beam
    widths at ``rho_c`` / ``rho_e``); ``depth_mm`` of range from ``top_mm``; ``n_lines`` lines and ``n_frames``
    frames centred on 0.  ``lines_per_beam``: each beam's -6 dB width is at least this many line (frame) spacings
    at ``rho_c`` (``rho_e``), as :func:`forward.beam.make_beam_pair`; None: the probe's widths.  Scatterers at x >= 0,
    the density raised by the fan's divergence at the top (at most ``density_factor_max`` times) so the speckle is
    developed at every depth.  Noise and seeding as :func:`forward.volume.make_volume_sequence` (the scatterers,
    then the noise of each volume; the pair of :func:`make_swept_pair` is this sequence's first two volumes)."""
    from femreg import Swept

    if not isinstance(geometry, Swept):
        raise ValueError("a swept volume needs a femreg.Swept geometry; use forward.volume for a Cartesian grid")
    geo = geometry
    pr = as_volume_probe(probe)
    fs = [_as_field3(f) for f in (fields if isinstance(fields, (list, tuple)) else [fields])]
    if not fs:
        raise ValueError("fields: at least one frame-0 -> frame-k field")
    snr_db = _snr(snr_db)
    n_lines, n_frames = int(n_lines), int(n_frames)
    if n_lines < 8 or n_frames < 8:
        raise ValueError(f"n_lines and n_frames must be >= 8, got {n_lines} and {n_frames}")
    dr = pr.spacing[0]
    n_s = max(8, int(round(float(depth_mm) / dr)))
    top = float(top_mm)
    r_mid = top + 0.5 * (n_s - 1) * dr
    if geo.array is None:
        dl, line_pitch, y0 = pr.pitch_mm, pr.pitch_mm, -0.5 * (n_lines - 1) * pr.pitch_mm
        rho_c, grow_l = None, 1.0
    else:
        rho_c = geo.array.radius_mm + r_mid
        dl, line_pitch, y0 = rho_c * geo.array.pitch_rad, float(geo.array.angle_pitch_deg), 0.0
        grow_l = rho_c / (geo.array.radius_mm + top)
    a_mid = r_mid if geo.array is None else float(geo.array.to_physical(r_mid, 0.0)[0])
    rho_e = geo.sweep_radius_mm + a_mid
    ds = rho_e * geo.step_rad
    grid = ImagingVolume((n_s, n_lines, n_frames), (dr, dl, ds),
                         (top, y0 if geo.array is None else -0.5 * (n_lines - 1) * dl, -0.5 * (n_frames - 1) * ds))
    if lines_per_beam is not None:
        k = float(lines_per_beam)
        pr = replace(pr, beam_fwhm_mm=max(pr.beam_fwhm_mm, k * dl), elevation_fwhm_mm=max(pr.elevation_fwhm_mm, k * ds))
    psf = pr.psf()
    hx, hy, hz = psf.half_support_mm(top + depth_mm)
    sp_s = (dr, line_pitch, float(geo.angle_step_deg))
    org_s = (top, y0, 0.0)
    X = geo.sample_positions((n_s, n_lines, n_frames), sp_s, org_s)
    P = np.column_stack([c.ravel()[::11] for c in X])
    umax = np.max([np.nanmax(np.abs(np.asarray(f.displacement(P), float)), axis=0) for f in fs], axis=0)
    grow_e = (geo.sweep_radius_mm + top + depth_mm) / rho_e
    m = umax + np.array([hx, hy * max(1.0, (geo.array.radius_mm + top + depth_mm) / rho_c if rho_c else 1.0),
                         hz * grow_e]) + 0.5
    box = (max(0.0, X[0].min() - m[0]), X[0].max() + m[0], X[1].min() - m[1], X[1].max() + m[1],
           X[2].min() - m[2], X[2].max() + m[2])
    del X, P
    # the beam-space cell at the top covers less tissue than at rho_e (rho_c): more scatterers keep it developed
    factor = min(float(density_factor_max), rho_e / (geo.sweep_radius_mm + top) * grow_l)
    dens = pr.density_per_mm3() * factor
    ss_scat, ss_noise = np.random.SeedSequence(_seed(seed)).spawn(2)
    sig = np.array([psf.sigma_axial_mm, float(psf.sigma_lateral_mm()), float(psf.sigma_elevational_mm())])
    scat = make_scatterers_3d(np.random.default_rng(ss_scat), box, density_per_mm3=dens, cell_aspect=sig)
    inside = getattr(fs[0], "inside", None)
    if callable(inside):
        scat.amplitudes[np.asarray(inside(scat.positions), bool)] *= 2.0
    n = len(fs) + 1
    frames = np.empty((n,) + grid.shape, np.float32)
    sigma = 0.0
    noise_rngs = [np.random.default_rng(s) for s in ss_noise.spawn(n)]
    for k, fk in enumerate([_Zero()] + fs):
        u = np.asarray(fk.displacement(scat.positions), float)
        if not np.all(np.isfinite(u)):
            raise ValueError(f"field {getattr(fk, 'name', fk)!r} is not finite at the scatterers")
        q = scat.positions + u
        r, line, phi = geo.to_beam(q[:, 0], q[:, 1], q[:, 2])
        b = np.column_stack([r, line if geo.array is None else rho_c * line, rho_e * phi])
        clean = render_volume(b, scat.amplitudes, grid, psf, dtype=np.float64)
        if k == 0 and snr_db is not None:
            sigma = noise_sigma(float(np.mean(clean ** 2)), snr_db)
        if sigma > 0:
            clean += sigma * noise_rngs[k].standard_normal(clean.shape)
        frames[k] = clean
    params = dict(probe=pr.to_dict(), psf=psf.to_dict(), geometry=geo.to_dict(), depth_mm=float(depth_mm),
                  n_lines=n_lines, n_frames=n_frames, top_mm=top, snr_db=snr_db, seed=int(seed),
                  n_scatterers=len(scat), density_per_mm3=dens, scatterer_box_mm=[float(v) for v in box],
                  noise_sigma=sigma, grid=grid.to_dict(), field=[getattr(f, "name", "custom") for f in fs])
    return SweptSequence(frames=frames, grid=grid, fields=[_Zero()] + fs, params=params, geometry=geo,
                         sample_spacing=sp_s, sample_origin=org_s)
