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

__all__ = ["remodulate", "baseband", "iq_convention", "SOUND_SPEED", "SAMPLES_PER_PERIOD"]

#: Default speed of sound, m/s.
SOUND_SPEED = 1540.0
#: Least RF samples per period (in depth) after remodulation.  The registration interpolates the RF with cubic
#: B-splines; at 4 samples per period their error is a few per cent of the amplitude, at 8 well under one.
SAMPLES_PER_PERIOD = 8


#: Demodulation frequencies above this (MHz) belong to no ultrasound probe: a value in Hz where MHz are asked
#: (4e6 for 4 MHz) would otherwise upsample each line a million-fold (an RF period of 0.2 nm).
MAX_MODULATION_MHZ = 100.0
#: Sound speeds (m/s) of soft tissue, water, phantoms and bone lie well inside this range; outside it the number
#: is in other units (1.54 km/s, 1.54e6 mm/s).
SOUND_SPEED_RANGE = (1000.0, 5000.0)


def check_modulation_frequency(f) -> float:
    """``f`` (MHz) as a float; an :class:`InputError` naming the value in MHz when it looks given in Hz or kHz."""
    from ..errors import pass_as

    f = float(f)
    if not (np.isfinite(f) and f > 0):
        raise InputError(pass_as(f"modulation_frequency must be a positive number (MHz), got {f!r}",
                                 f"--iq-frequency must be a positive number (MHz), got {f:g}"))
    if f > MAX_MODULATION_MHZ:
        for k, unit in ((1e6, "Hz"), (1e3, "kHz")):
            if 0.5 <= f / k <= MAX_MODULATION_MHZ:
                raise InputError(pass_as(
                    f"modulation_frequency {f:g} MHz is above any ultrasound probe's ({MAX_MODULATION_MHZ:g} MHz "
                    f"at most): it looks given in {unit}; pass it in MHz, modulation_frequency={f / k:g} "
                    f"(CLI: --iq-frequency {f / k:g})",
                    f"--iq-frequency {f:g} MHz is above any ultrasound probe's ({MAX_MODULATION_MHZ:g} MHz at "
                    f"most): it looks given in {unit}; pass it in MHz, --iq-frequency {f / k:g}"))
        raise InputError(pass_as(f"modulation_frequency {f:g} MHz is above any ultrasound probe's "
                                 f"({MAX_MODULATION_MHZ:g} MHz at most)",
                                 f"--iq-frequency {f:g} MHz is above any ultrasound probe's "
                                 f"({MAX_MODULATION_MHZ:g} MHz at most)"))
    return f


def check_sound_speed(c) -> float:
    """``c`` (m/s) as a float; an :class:`InputError` naming the value in m/s when it looks given in km/s or
    mm/s."""
    from ..errors import pass_as

    c = float(c)
    lo, hi = SOUND_SPEED_RANGE
    if np.isfinite(c) and lo <= c <= hi:
        return c
    if not (np.isfinite(c) and c > 0):
        raise InputError(pass_as(f"sound_speed must be a finite number > 0 (m/s), got {c:g}",
                                 f"--sound-speed must be a finite number > 0 (m/s), got {c:g}"))
    hint = next((f": it looks given in {unit}; pass it in m/s, " + pass_as(f"sound_speed={c * k:g} (CLI: "
                 f"--sound-speed {c * k:g})", f"--sound-speed {c * k:g}")
                 for k, unit in ((1e3, "km/s"), (1e-3, "mm/s")) if np.isfinite(c) and lo <= c * k <= hi), "")
    raise InputError(pass_as(f"sound_speed {c:g} m/s", f"--sound-speed {c:g} m/s")
                     + f" is outside the speeds of sound in tissue, water and phantoms ({lo:g}-{hi:g} m/s; soft "
                       f"tissue about 1540){hint}")


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
    check_modulation_frequency(f)
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


def baseband(rf, axial_spacing, modulation_frequency, *, axial_origin=0.0, sound_speed=SOUND_SPEED, axis=-2):
    """The IQ samples of RF (the inverse of :func:`remodulate` without the decimation): analytic signal along
    ``axis`` shifted down by ``modulation_frequency`` (MHz); spacing mm, ``c`` m/s."""
    from scipy.signal import hilbert

    rf = np.asarray(rf, float)
    z = float(axial_origin) + float(axial_spacing) * np.arange(rf.shape[axis])
    shape = [1] * rf.ndim
    shape[axis] = z.size
    return hilbert(rf, axis=axis) * np.exp(-2j * np.pi * float(modulation_frequency) * 2e3 * z
                                           / float(sound_speed)).reshape(shape)


#: Axial window of the sign-convention check, in IQ samples, and its step.
CONVENTION_WINDOW = 32
#: Windows whose envelope correlation peak is below this are left out of the convention check.
CONVENTION_MIN_NCC = 0.6
#: The convention is decided when one sign explains the windows' phases this much better (ratio of the phase
#: misfits) and enough windows (:data:`CONVENTION_MIN_WINDOWS`) moved by a measurable fraction of a sample.
CONVENTION_RATIO = 2.0
CONVENTION_MIN_WINDOWS = 20
#: Phase misfit (mean of 1 - cos) added to both signs' before their ratio, so that frames without motion (both
#: near zero) give no verdict.
CONVENTION_FLOOR = 1e-4
#: Windows looked at, at most (spread over the depth and the groups of lines).
CONVENTION_WINDOWS = 400


def iq_convention(iq_a, iq_b, axial_spacing, modulation_frequency, *, sound_speed=SOUND_SPEED):
    """Which sign the IQ data were demodulated with, from two frames ``(axial, lateral)`` of tissue in motion.

    Between frames, tissue that moves by ``u`` along depth shifts the envelope by ``u`` and, after that shift, turns
    the IQ phase by ``-4 pi f u / c`` (standard convention) or ``+4 pi f u / c`` (conjugate).  In windows of
    :data:`CONVENTION_WINDOW` samples (summed over groups of lines, the lag followed down the depth) the envelope
    correlation's peak ``L`` (parabolic sub-sample) gives ``u``, and the phase of the complex cross-correlation at
    ``L`` is compared, modulo 2 pi, with what each sign predicts from it.  The sign that predicts the phases is the
    convention.

    The same phases tell the demodulation frequency: with the wrong one the RF carrier's phase is read with the
    wrong wavelength and the strain comes out scaled by about ``f_true / f_given`` (a 20 % error in ``f`` gave
    17-25 % in the strain, ``success=True``).  Every signed frequency from ``f / 4`` to ``4 f`` is scored (negative:
    the conjugate sign).

    Returns ``(verdict, ratio, n, f_best)``: ``ratio`` the phase misfit (mean of ``1 - cos`` of the difference,
    plus :data:`CONVENTION_FLOOR`) of the conjugate sign over the standard one at ``f``, ``n`` the windows used,
    ``f_best`` the best signed frequency (MHz).  ``verdict``: "standard" / "conjugate" when that sign explains the
    phases :data:`CONVENTION_RATIO` times better than the other and within that factor of the best frequency;
    "frequency" when neither sign at ``f`` comes within that factor of the best, more than 5 % away, and the
    windows' shifts spread over half a turn of the phase at ``f`` (less motion cannot tell a frequency); "unknown"
    otherwise (fewer than :data:`CONVENTION_MIN_WINDOWS` windows correlate, no motion between the frames, or too
    little to tell).
    """
    a, b = np.asarray(iq_a), np.asarray(iq_b)
    w = CONVENTION_WINDOW
    # phase turned by a one-sample shift: 4 pi f dz / c (f MHz, dz mm, c m/s -> rad)
    per_sample = 4.0 * np.pi * float(modulation_frequency) * float(axial_spacing) * 1e3 / float(sound_speed)
    reach = w // 2                      # lags searched around the window above's (displacement is continuous)
    group = max(4, a.shape[1] // 8)     # lines summed per window
    per_group = CONVENTION_WINDOWS // max(1, a.shape[1] // group)
    step = max(w // 2, (a.shape[0] - w) // max(1, per_group))
    shifts, phases = [], []
    for j0 in range(0, a.shape[1] - group + 1, group):
        la = a[:, j0:j0 + group]
        lb = np.lib.stride_tricks.sliding_window_view(b[:, j0:j0 + group], w, axis=0)   # (n - w + 1, group, w)
        centre = 0
        for z0 in range(0, a.shape[0] - w + 1, step):
            lags = np.arange(max(centre - reach, -z0), min(centre + reach, lb.shape[0] - 1 - z0) + 1)
            if lags.size < 3:
                continue
            wa = la[z0:z0 + w].T                                   # (group, w)
            wb = lb[z0 + lags]                                     # (lags, group, w)
            R = np.einsum("lgw,gw->l", wb, np.conj(wa))
            ea = np.abs(wa)
            ea = ea - ea.mean(axis=1, keepdims=True)
            eb = np.abs(wb)
            eb = eb - eb.mean(axis=2, keepdims=True)
            E = np.einsum("lgw,gw->l", eb, ea) / (np.sqrt(np.sum(ea ** 2) * np.sum(eb ** 2, axis=(1, 2))) + 1e-30)
            i = int(np.argmax(E))
            if not (0 < i < E.size - 1) or E[i] < CONVENTION_MIN_NCC:
                continue
            centre = int(lags[i])
            den = E[i - 1] - 2 * E[i] + E[i + 1]
            frac = 0.5 * (E[i - 1] - E[i + 1]) / den if den < 0 else 0.0
            shifts.append(lags[i] + frac)                          # envelope shift, samples
            phases.append(float(np.angle(R[i])))                   # standard: -per_sample * shift (mod 2 pi)
    n = len(shifts)
    if n < CONVENTION_MIN_WINDOWS:
        return "unknown", float("nan"), n, float("nan")
    u, ph = np.asarray(shifts), np.asarray(phases)

    def misfit(freqs):      # phase misfit (mean 1 - cos) of each signed frequency (MHz), plus the floor
        k = 4.0 * np.pi * np.asarray(freqs, float) * float(axial_spacing) * 1e3 / float(sound_speed)
        return np.mean(1.0 - np.cos(ph[None, :] + k[:, None] * u[None, :]), axis=1) + CONVENTION_FLOOR

    f = float(modulation_frequency)
    grid = f * np.exp(np.linspace(np.log(0.25), np.log(4.0), 1109))        # 0.25 % steps
    grid = np.concatenate([grid, -grid])
    m_grid = misfit(grid)
    best = int(np.argmin(m_grid))
    f_best = float(grid[best])
    m_std, m_conj = misfit([f, -f])
    if m_std * CONVENTION_RATIO <= m_conj and m_std <= CONVENTION_RATIO * m_grid[best]:
        return "standard", float(m_conj / m_std), n, f_best
    if m_conj * CONVENTION_RATIO <= m_std and m_conj <= CONVENTION_RATIO * m_grid[best]:
        return "conjugate", float(m_conj / m_std), n, f_best
    # the frequency shows only when the windows' shifts spread over half a turn of the phase at least
    turns = np.ptp(u) * 4.0 * np.pi * max(f, abs(f_best)) * float(axial_spacing) * 1e3 / float(sound_speed)
    if (turns >= np.pi and min(m_std, m_conj) >= CONVENTION_RATIO * m_grid[best]
            and abs(abs(f_best) / f - 1.0) > 0.05):
        return "frequency", float(m_conj / m_std), n, f_best
    return "unknown", float(m_conj / m_std), n, f_best
