"""What an RF image says about its own scale: the envelope (:func:`envelope`, the magnitude of the analytic signal
along each line), the axial RF period (:func:`rf_period`, 1 / spectral centroid) and the speckle and pulse cell
sizes (:func:`speckle_statistics`), all in mm.  The pyramid (:mod:`femreg.pyramid`) sizes its mesh, windows and
searches from them, the repair stage uses the period; :mod:`forward` and the plots use the envelope.
"""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field

import numpy as np

from . import _kernels

__all__ = ["SpeckleStats", "envelope", "rf_period", "speckle_statistics", "speckle_cell", "STRUCTURE_WINDOW_MM"]


@dataclass
class SpeckleStats:
    """What the image itself says about its scale (mm): ``period`` = axial RF period (1 / spectral centroid),
    ``cell`` = (axial, lateral) full width at half maximum of the envelope autocorrelation, ``pulse_cell`` the
    same width computed from the RF (analytic-signal) autocorrelation, ``|rho|^2`` (None: not measured).  On fully
    developed speckle the two agree (the envelope's autocovariance is ``|rho|^2``); on tissue the envelope also
    holds the echo structure (layers, fibres) and ``cell`` grows with it while ``pulse_cell`` stays the pulse's
    (in vivo 4 MHz frames: cell 0.76-1.0 x 2.4-3.2 mm, pulse_cell 0.20-0.24 x 0.4 mm).  ``envelope`` is the
    image's envelope (:func:`envelope`), kept so that the pyramid does not compute it again."""

    period: float
    cell: np.ndarray
    envelope: np.ndarray | None = dc_field(default=None, repr=False, compare=False)
    pulse_cell: np.ndarray | None = None


def _analytic(img, complex_signal: bool = False, power: bool = False):
    """Axial half spectrum of ``img`` zero-padded to ``nf`` samples (a fast FFT length >= n_axial), ``nf``, and
    the envelope |analytic signal| (the transform of scipy.signal.hilbert); with ``complex_signal`` the analytic
    signal itself instead of its modulus; with ``power`` the spectrum's |X|^2 instead of the spectrum.

    The analytic signal is ``img + i H[img]``; its imaginary part, the Hilbert transform, is one real inverse
    transform of ``-i sign(f) X`` (DC and Nyquist bins zero), which is what scipy.signal.hilbert's complex
    inverse FFT computes, at half the cost.  The zero padding replaces the circular wrap of the end samples by
    zeros (within a pulse length of the top and bottom rows) and avoids FFT lengths with large prime factors
    (e.g. 1948 = 4 x 487 rows, several times slower).  Compiled, the spectrum product and the
    modulus are single passes (the same values as numpy's)."""
    from scipy import fft as sfft

    m = img.shape[0]
    nf = sfft.next_fast_len(m, real=True)
    Xr = sfft.rfft(img, n=nf, axis=0)
    if _kernels.use_compiled():
        P = np.empty(Xr.shape) if power else np.empty((0, 0))
        hil = sfft.irfft(_kernels.hilbert_half_spectrum(Xr, (nf + 1) // 2, P), n=nf, axis=0)
        sig = _kernels.to_complex(img, hil) if complex_signal else _kernels.modulus(img, hil)
        return (P if power else Xr), nf, sig
    s = np.zeros(Xr.shape[0], complex)
    s[1:(nf + 1) // 2] = -1j                      # positive frequencies, DC and Nyquist excluded
    hil = sfft.irfft(Xr * s[:, None], n=nf, axis=0)[:m]
    sig = img + 1j * hil if complex_signal else np.sqrt(img * img + hil * hil)
    return (Xr.real ** 2 + Xr.imag ** 2 if power else Xr), nf, sig


def envelope(image) -> np.ndarray:
    """Envelope ``|analytic signal|`` along the axial direction (as scipy.signal.hilbert, zero-padded to a fast FFT
    length)."""
    return _analytic(np.asarray(image, float))[2]


def _centroid_period(power, n: int, dx: float) -> float:
    """1 / spectral centroid (mm) of a line-averaged axial power spectrum (n samples, DC bin ignored)."""
    P = np.array(power, float)
    P[0] = 0.0                                        # the line means (DC) carry no period
    f = np.fft.rfftfreq(n, dx)
    fc = float(np.sum(f * P) / np.sum(P)) if np.sum(P) > 0 else 0.0
    return 1.0 / fc if fc > 0 else float(n * dx)


def rf_period(image, spacing) -> float:
    """Axial RF period (mm) alone, as in :func:`speckle_statistics` (one real FFT, no envelope)."""
    from scipy import fft as sfft

    img = np.asarray(image, float)
    nf = sfft.next_fast_len(img.shape[0], real=True)     # zero-padded as in speckle_statistics
    P = np.mean(np.abs(sfft.rfft(img, n=nf, axis=0)) ** 2, axis=1)
    return _centroid_period(P, nf, float(spacing[0]))


def _half_width(ac, d) -> float:
    """Full width (mm) at half maximum of a one-sided autocorrelation ``ac`` (lag 0 first), lag step ``d``."""
    ac = ac / ac[0] if ac[0] > 0 else ac
    below = np.flatnonzero(ac < 0.5)
    return 2.0 * (below[0] if below.size else len(ac)) * d


def _envelope_cell(e, axis: int, d: float, direct_lags: int = 48, chunk: int = 4) -> float:
    """:func:`_half_width` of the line-summed linear autocorrelation of ``e`` along ``axis``.

    Lag by lag (one product per lag; compiled, ``chunk`` lags per pass over the image) while the half maximum
    has not been crossed, which on speckle takes a few lags (a speckle cell is ~6-20 samples wide); past
    ``direct_lags`` lags, the whole autocorrelation by a zero-padded FFT (Wiener-Khinchin), as before.  Both
    give the same sums (to round-off)."""
    from scipy import fft as sfft

    m = e.shape[axis]
    ea = np.moveaxis(e, axis, 0)
    a0 = float(np.vdot(ea, ea))
    if a0 > 0:
        if _kernels.use_compiled() and ea.flags.c_contiguous:
            for k0 in range(1, min(m, direct_lags), chunk):
                s = _kernels.lag_products(ea, k0, min(k0 + chunk, m, direct_lags))
                below = np.flatnonzero(s < 0.5 * a0)
                if below.size:
                    return 2.0 * (k0 + below[0]) * d
        else:
            for k in range(1, min(m, direct_lags)):
                if float(np.einsum("ij,ij->", ea[:-k], ea[k:])) < 0.5 * a0:
                    return 2.0 * k * d
    nf = sfft.next_fast_len(2 * m, real=True)           # >= 2m - 1: linear (not circular) correlation to lag m
    F = sfft.rfft(e, n=nf, axis=axis)
    return _half_width(sfft.irfft(np.mean(F.real ** 2 + F.imag ** 2, axis=1 - axis), n=nf)[:m], d)


def speckle_statistics(image, spacing) -> SpeckleStats:
    """RF period from the axial power spectrum's centroid; speckle cell from the envelope autocorrelation and
    pulse cell from the analytic signal's, ``|rho|^2`` (FFT, zero-padded, averaged over lines / rows), all in mm.
    The line average is taken on the power spectra (one inverse transform; the same by linearity)."""
    from scipy import fft as sfft

    img = np.asarray(image, float)
    dx, dy = float(spacing[0]), float(spacing[1])
    P, n, a = _analytic(img, complex_signal=True, power=True)
    env = np.abs(a)
    power = np.mean(P, axis=1)                                    # line-averaged axial power spectrum (n bins)
    period = _centroid_period(power, n, dx)
    e = env - env.mean()
    cell, pulse = [_envelope_cell(e, 0, dx), _envelope_cell(np.ascontiguousarray(e.T), 0, dy)], []
    # pulse cell: axially from the one-sided power spectrum (Wiener-Khinchin; circular, the pulse is short),
    # laterally lag by lag on every 4th row until |rho|^2 < 1/2 (a few lines; cheaper than a padded complex FFT)
    spec = np.zeros(n)
    spec[1:(n + 1) // 2] = power[1:(n + 1) // 2]
    rho = sfft.ifft(spec)
    pulse.append(_half_width(np.abs(rho[:n // 2]) ** 2, dx))
    rows = a[::4]
    r0 = float(np.sum(np.abs(rows) ** 2))
    k = 1
    while k < img.shape[1] and r0 > 0 and \
            abs(np.vdot(rows[:, :-k], rows[:, k:])) ** 2 >= 0.5 * r0 ** 2:
        k += 1
    pulse.append(2.0 * k * dy)
    return SpeckleStats(period=period, cell=np.array(cell), envelope=env, pulse_cell=np.array(pulse))


#: Window (axial, lateral) mm over which :func:`speckle_cell` normalises the envelope by its local RMS: several
#: speckle cells of any probe here (the 3 MHz beam's 3 mm lateral cell fits three times), so uniform speckle keeps
#: its cell, while tissue structure larger than it is divided out.
STRUCTURE_WINDOW_MM = (5.0, 10.0)


def speckle_cell(image, spacing, window=STRUCTURE_WINDOW_MM, stats: SpeckleStats | None = None) -> np.ndarray:
    """(axial, lateral) speckle cell (mm, (2,)) of the speckle itself: the envelope autocorrelation FWHM, as
    :attr:`SpeckleStats.cell`, of the envelope divided by its local RMS over ``window`` (mm, axial and lateral).

    Why: :func:`speckle_statistics`'s cell reads the whole envelope, so tissue structure (bright layers, a
    brightness falling with depth) widens it: on the in vivo frames 0.72-0.92 x 2.4-3.2 mm, where this reads 0.48 x
    0.80 mm.  Simulated (forward.pairs, 1 % compression, 30 dB): uniform speckle under 3-12 MHz reads the same cell
    both ways (0.15-0.62 x 0.60-3.00 mm); with a layered echogenicity of 6 dB RMS in 2 x 10 mm patches the whole
    envelope reads 1.31-1.58 x 4.8-5.2 mm and this the uniform speckle's cell exactly; patches of 1 x 8 mm or 12 dB
    leave it 15-43 % wide (against 1.7-10x).  ``stats``: the image's :func:`speckle_statistics`, if already
    computed (its envelope is reused)."""
    from scipy.ndimage import uniform_filter

    dx, dy = float(spacing[0]), float(spacing[1])
    env = (stats if stats is not None else speckle_statistics(image, spacing)).envelope
    w = (max(3, int(round(float(window[0]) / dx))), max(3, int(round(float(window[1]) / dy))))
    # no echo (zero fill below the echo, a fan's wedge) is left out of the local RMS (normalised convolution) and
    # left at zero: neither a block of constant envelope nor a brightened rim along its border
    echo = env > 1e-3 * float(np.median(env[env > 0])) if np.any(env > 0) else env > 0
    if echo.all():      # echo everywhere (most frames): the same values without the masks (share is exactly 1)
        e = env / np.sqrt(uniform_filter(env * env, w, mode="reflect"))
        e -= float(np.mean(e))
        return np.array([_envelope_cell(e, 0, dx), _envelope_cell(np.ascontiguousarray(e.T), 0, dy)])
    share = uniform_filter(echo.astype(float), w, mode="reflect")
    valid = echo & (share > 0.25)
    if not np.any(valid):
        return np.array([np.nan, np.nan])
    local = np.sqrt(uniform_filter(np.where(echo, env * env, 0.0), w, mode="reflect") / np.maximum(share, 1e-12))
    e = np.where(valid, env / np.where(valid, local, 1.0), 0.0)
    e = np.where(valid, e - float(np.mean(e[valid])), 0.0)
    return np.array([_envelope_cell(e, 0, dx), _envelope_cell(np.ascontiguousarray(e.T), 0, dy)])
