"""Small seeded RF volumes for the volume-registration tests and benchmark: point scatterers imaged with a
separable PSF (Gaussian-modulated axial pulse, Gaussian lateral and elevational beams), the moving volume from the
same scatterers moved by an exact field (``reference(x) ~ moving(x + u(x))``)."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

C_MM_PER_US = 1.54          # speed of sound, mm / us


def _taps(coords, pos, width, fn):
    """Grid indices (n_scat, k) and values fn(coords[i] - pos[s]) of the samples within +-width (0 elsewhere)."""
    lo = np.searchsorted(coords, pos - width)
    hi = np.minimum(np.searchsorted(coords, pos + width), coords.size)
    k = max(1, int(np.max(hi - lo))) if pos.size else 1
    idx = lo[:, None] + np.arange(k)[None, :]
    ok = idx < hi[:, None]
    idx = np.where(ok, idx, 0)
    return idx, np.where(ok, fn(coords[idx] - pos[:, None]), 0.0)


def render(scat, amp, axes, f_mhz, lat_fwhm, elev_fwhm, cycles=2.0, chunk=20000):
    """RF volume on the grid ``axes`` (x, y, z mm) of scatterers (n, 3) mm with amplitudes (n,): the sum of
    separable PSFs, as sparse products (axial taps) x (lateral x elevational taps)."""
    lam = C_MM_PER_US / f_mhz
    k0 = 4 * np.pi / lam                                # pulse-echo carrier, rad / mm
    sx = cycles * lam / 2 / 2.355                       # axial envelope sigma (mm): pulse of ~cycles periods
    sy, sz = lat_fwhm / 2.355, elev_fwhm / 2.355
    x, y, z = axes
    out = np.zeros((x.size, y.size * z.size))
    for s0 in range(0, len(scat), chunk):
        p = scat[s0:s0 + chunk]
        a = amp[s0:s0 + chunk]
        n = p.shape[0]
        ix, vx = _taps(x, p[:, 0], 4 * sx, lambda d: np.exp(-0.5 * (d / sx) ** 2) * np.cos(k0 * d))
        iy, vy = _taps(y, p[:, 1], 4 * sy, lambda d: np.exp(-0.5 * (d / sy) ** 2))
        iz, vz = _taps(z, p[:, 2], 4 * sz, lambda d: np.exp(-0.5 * (d / sz) ** 2))
        Ax = sp.csr_matrix((vx.ravel(), (ix.ravel(), np.repeat(np.arange(n), ix.shape[1]))), shape=(x.size, n))
        cols = (iy[:, :, None] * z.size + iz[:, None, :]).reshape(n, -1)
        vals = (a[:, None, None] * vy[:, :, None] * vz[:, None, :]).reshape(n, -1)
        B = sp.csr_matrix((vals.ravel(), (np.repeat(np.arange(n), cols.shape[1]), cols.ravel())),
                          shape=(n, y.size * z.size))
        out += (Ax @ B).toarray()
    return out.reshape(x.size, y.size, z.size)


def _scene(shape, spacing, f_mhz, lat_fwhm, elev_fwhm, density, rng):
    """Scatterers (n, 3) mm and amplitudes (n,) over the grid of ``shape`` and ``spacing`` plus a PSF's pad, the
    grid's axes and the lateral and elevational beam FWHM (mm)."""
    lam = C_MM_PER_US / f_mhz
    lat = lat_fwhm if lat_fwhm is not None else max(1.5 * lam, 3.0 * spacing[1])
    ele = elev_fwhm if elev_fwhm is not None else max(2.5 * lam, 3.0 * spacing[2])
    axes = [spacing[a] * np.arange(shape[a]) for a in range(3)]
    pad = np.array([1.0, 1.0, 1.0]) + np.array([0.0, lat, ele])
    lo = np.array([a[0] for a in axes]) - pad
    hi = np.array([a[-1] for a in axes]) + pad
    n = rng.poisson(density * np.prod(hi - lo))
    X = lo + (hi - lo) * rng.random((n, 3))
    amp = rng.standard_normal(n)
    return X, amp, axes, lat, ele


def volume_pair(field, *, shape=(200, 24, 20), spacing=(0.02, 0.2, 0.25), f_mhz=7.0, lat_fwhm=None,
                elev_fwhm=None, density=60.0, seed=0, snr_db=None):
    """``(ref, mov, spacing, origin)`` for ``field`` callable (n, 3) mm -> (n, 3) mm.  Beam widths default to
    about 1.5 wavelengths laterally and 2.5 elevationally (at least 1.5 pitches); ``density`` scatterers / mm^3."""
    rng = np.random.default_rng(seed)
    spacing = np.asarray(spacing, float)
    X, amp, axes, lat, ele = _scene(shape, spacing, f_mhz, lat_fwhm, elev_fwhm, density, rng)
    ref = render(X, amp, axes, f_mhz, lat, ele)
    mov = render(X + np.asarray(field(X), float), amp, axes, f_mhz, lat, ele)
    if snr_db is not None:
        s = np.sqrt(np.mean(ref ** 2)) * 10 ** (-snr_db / 20)
        ref = ref + s * rng.standard_normal(ref.shape)
        mov = mov + s * rng.standard_normal(mov.shape)
    return ref, mov, spacing, np.zeros(3)


def compression_sequence(compressions, *, shape=(300, 30, 24), spacing=(0.02, 0.2, 0.25), f_mhz=7.0, seed=0):
    """A volume sequence (n_frames, n_x, n_y, n_z) of one scatterer set under uniaxial compression: frame k
    compressed axially by ``compressions[k]`` (fraction; frame 0 usually 0) about the grid's centre, with a
    lateral and elevational expansion of half of it.  Returns ``(frames, spacing, field)``, ``field(k, X)`` the
    exact displacement (n, 3) mm from frame 0 to frame k at frame-0 positions X (n, 3) mm."""
    rng = np.random.default_rng(seed)
    spacing = np.asarray(spacing, float)
    X, amp, axes, lat, ele = _scene(shape, spacing, f_mhz, None, None, 60.0, rng)
    centre = np.asarray(shape) * spacing / 2

    def field(k, P):
        return (np.asarray(P, float) - centre) * (compressions[k] * np.array([-1.0, 0.5, 0.5]))

    frames = np.stack([render(X + field(k, X), amp, axes, f_mhz, lat, ele) for k in range(len(compressions))])
    return frames, spacing, field


def affine_field(compression=0.01, shear=0.005, rotation_deg=0.5, centre=(2.0, 2.4, 2.5)):
    """Exact affine u(X) = (F - I)(X - c): axial compression with a Poisson lateral / elevational expansion of
    half of it, a shear exy and a rotation about the elevational axis.  Returns ``(field, grad)`` with ``grad``
    the constant displacement gradient (3, 3)."""
    th = np.deg2rad(rotation_deg)
    R = np.array([[np.cos(th), -np.sin(th), 0.0], [np.sin(th), np.cos(th), 0.0], [0.0, 0.0, 1.0]])
    E = np.diag([-compression, 0.5 * compression, 0.5 * compression])
    E[0, 1] = E[1, 0] = shear
    G = R @ (np.eye(3) + E) - np.eye(3)
    c = np.asarray(centre, float)

    def field(X):
        return (np.asarray(X, float) - c) @ G.T

    return field, G
