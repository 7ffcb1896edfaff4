"""IQ (complex baseband) beamformed data -> RF, the samples femreg registers.

Many scanners and research platforms export beamformed frames as IQ: the analytic RF signal shifted down by the
demodulation (modulation) frequency ``f`` and usually decimated along depth.  The RF is restored by shifting it
back up,

    rf(z) = Re{ iq(z) exp(2 pi i f 2 z / c) },

with ``z`` the depth of the sample (two-way time ``2 z / c``), after band-limited upsampling
(:func:`scipy.signal.resample_poly`) along the depth when the IQ grid has fewer than
:data:`SAMPLES_PER_PERIOD` samples per RF period ``c / (2 f)``.  The sign convention is the usual one (IQ =
RF analytic signal times ``exp(-2 pi i f t)``); data demodulated with the opposite sign are the complex conjugate,
which :func:`remodulate` takes with ``conjugate=True``.

Units: depth and spacing in mm, ``f`` in MHz, ``c`` in m/s.  The phase is referenced to depth 0 (the array face);
a constant phase offset changes the RF's phase, not the displacement measured between two frames.
"""
from __future__ import annotations

import numpy as np

from ..errors import InputError

__all__ = ["remodulate", "SOUND_SPEED", "SAMPLES_PER_PERIOD"]

#: Default speed of sound, m/s.
SOUND_SPEED = 1540.0
#: Least RF samples per period (in depth) after remodulation.  The registration interpolates the RF with cubic
#: B-splines; at 4 samples per period their error is a few per cent of the amplitude, at 8 well under one.
SAMPLES_PER_PERIOD = 8


def remodulate(iq, axial_spacing, modulation_frequency, *, axial_origin=0.0, sound_speed=SOUND_SPEED, axis=-2,
               conjugate=False, samples_per_period=SAMPLES_PER_PERIOD):
    """RF samples from IQ samples (module docstring).

    Parameters
    ----------
    iq : complex array
        IQ samples; ``axis`` is the depth (axial) axis (default -2: ``(..., axial, lateral)``).
    axial_spacing : float, mm
        Depth step of the IQ samples.
    modulation_frequency : float, MHz
        The demodulation frequency the IQ data were shifted by.
    axial_origin : float, mm
        Depth of the first sample.
    sound_speed : float, m/s
    conjugate : bool
        IQ demodulated with ``exp(+2 pi i f t)`` (the opposite convention).
    samples_per_period : int
        Least RF samples per RF period after upsampling.

    Returns
    -------
    rf : float array
        Same shape as ``iq`` except along ``axis``: ``(n - 1) * up + 1`` samples.
    spacing : float, mm
        Depth step of ``rf`` (``axial_spacing / up``).
    up : int
        Upsampling factor (1: none needed).
    """
    iq = np.asarray(iq)
    f, dz, c = float(modulation_frequency), float(axial_spacing), float(sound_speed)
    for name, v in (("modulation frequency (MHz)", f), ("axial spacing (mm)", dz), ("sound speed (m/s)", c)):
        if not (np.isfinite(v) and v > 0):
            raise InputError(f"{name} must be a positive number, got {v!r}")
    if not np.iscomplexobj(iq):
        raise InputError(f"IQ data must be complex, got {iq.dtype}")
    period = c / (2e3 * f)                       # mm of depth per RF period
    up = max(1, int(np.ceil(samples_per_period * dz / period)))
    n = iq.shape[axis]
    if conjugate:
        iq = np.conj(iq)
    if up > 1:
        from scipy.signal import resample_poly

        iq = resample_poly(iq, up, 1, axis=axis)
        iq = np.take(iq, np.arange((n - 1) * up + 1), axis=axis)
    z = float(axial_origin) + dz / up * np.arange(iq.shape[axis])
    shape = [1] * iq.ndim
    shape[axis] = z.size
    carrier = np.exp(2j * np.pi * f * 2e3 * z / c).reshape(shape)
    rf = np.real(iq * carrier)
    return rf.astype(np.float32 if iq.dtype == np.complex64 else np.float64, copy=False), dz / up, up
