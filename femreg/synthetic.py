"""Synthetic speckle image pairs with a known displacement, for tests and benchmarks (not the RF simulator).

The reference is white Gaussian scatterer noise on the pixel grid convolved with a separable PSF: a Gaussian-
modulated cosine axially (centre frequency ``f0``, pulse length ``pulse_us``) and a Gaussian laterally (FWHM
``lateral_fwhm``).  The moving image satisfies ``moving(x + u(x)) = reference(x)``: it is the reference sampled
at ``X(y)`` with ``X + u(X) = y`` (fixed-point inversion), using a quintic spline so that the warp does not share
the registration's cubic interpolant.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["speckle_image", "warp_image", "speckle_pair", "PAPER_SPACING", "PAPER_SHAPE"]

#: Paper sampling (axial 40 MHz at 1540 m/s, lateral 0.3 mm) and image size (72 x 44 mm).
PAPER_SPACING = (0.0192, 0.3)
PAPER_SHAPE = (3750, 147)


def speckle_image(shape, spacing, rng, *, f0_mhz: float = 5.5, pulse_us: float = 0.43, lateral_fwhm: float = 1.4,
                  c_m_s: float = 1540.0) -> np.ndarray:
    """RF-like speckle: scatterer noise convolved with a separable PSF, unit RMS.  ``rng``: numpy Generator."""
    dx, dy = spacing
    lam = c_m_s * 1e3 / (f0_mhz * 1e6)               # wavelength, mm
    sig_x = 0.5 * pulse_us * 1e-6 * c_m_s * 1e3 / 2.355  # Gaussian envelope, mm (pulse length ~ FWHM, round trip)
    sig_y = lateral_fwhm / 2.355
    hx = int(np.ceil(4 * sig_x / dx))
    hy = int(np.ceil(4 * sig_y / dy))
    x = np.arange(-hx, hx + 1) * dx
    y = np.arange(-hy, hy + 1) * dy
    px = np.exp(-0.5 * (x / sig_x) ** 2) * np.cos(2 * np.pi * x / (lam / 2))
    py = np.exp(-0.5 * (y / sig_y) ** 2)
    noise = rng.standard_normal(shape)
    img = ndimage.convolve1d(noise, px, axis=0, mode="wrap")
    img = ndimage.convolve1d(img, py, axis=1, mode="wrap")
    return img / np.sqrt(np.mean(img ** 2))


def warp_image(image, spacing, origin, displacement, *, iterations: int = 30, order: int = 5) -> np.ndarray:
    """Moving image with ``moving(x + u(x)) = image(x)``; ``displacement(points (n,2) mm) -> (n,2) mm``."""
    shape = image.shape
    spacing = np.asarray(spacing, float)
    origin = np.asarray(origin, float)
    ii, jj = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    y = np.column_stack([origin[0] + ii.ravel() * spacing[0], origin[1] + jj.ravel() * spacing[1]])
    X = y.copy()
    for _ in range(iterations):
        Xn = y - np.asarray(displacement(X), float)
        if np.max(np.abs(Xn - X)) < 1e-12:
            X = Xn
            break
        X = Xn
    idx = ((X - origin) / spacing).T
    coeffs = ndimage.spline_filter(image, order=order, mode="mirror")
    return ndimage.map_coordinates(coeffs, idx, order=order, mode="mirror", prefilter=False).reshape(shape)


def speckle_pair(displacement, shape=PAPER_SHAPE, spacing=PAPER_SPACING, origin=(0.0, 0.0), *, seed: int = 0,
                 snr_db: float | None = None, **psf):
    """(reference, moving) speckle pair related by ``displacement`` (callable), optional white noise at
    ``snr_db`` (independent in both frames)."""
    rng = np.random.default_rng(seed)
    ref = speckle_image(shape, spacing, rng, **psf)
    mov = warp_image(ref, spacing, origin, displacement)
    if snr_db is not None:
        s = 10 ** (-snr_db / 20.0)
        ref = ref + s * rng.standard_normal(shape)
        mov = mov + s * rng.standard_normal(shape)
    return ref, mov
