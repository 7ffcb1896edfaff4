"""Orientation and sampling checks of RF frames: does axis 0 carry the carrier, and is the axial spacing plausible?

femreg's arrays are (axial, lateral) = (x, y) with ``spacing = (dx, dy)`` mm.  Two mistakes give a plausible-looking
but wrong registration (the compression lands in the lateral strain, an inclusion becomes a streak): frames stored
lines x samples (transposed) and the two spacings exchanged.  The RF itself tells them apart:

* **carrier** -- along the axial direction RF is a band-pass signal: its line-averaged power spectrum (the one the
  RF period of :func:`femreg.speckle.rf_period` is the centroid of) has almost no power below a third of its
  centroid frequency; across lines the speckle is low-pass (the beam profile), with most power near zero.
  :func:`carrier_ratio` is that low-band to centre-band power ratio: 0.000-0.027 along the axial axis of simulated
  3-15 MHz probes (SNR 10-40 dB) and of the in vivo 4 MHz frames, 0.58-2.1 across their lines, 1.2 or more along
  both axes of their envelopes (benchmarks/orientation_check.py); across only 16-20 lines (narrow frames, coarse
  pitch) it falls to 0.3-0.7, and below :data:`MIN_SAMPLES` it is not measured.  A carrier across the lines and
  none along them is a transposed frame.
* **centre frequency** -- the RF period ``T`` (mm of depth) from :func:`femreg.speckle.speckle_statistics` gives
  ``f = c / (2 T)`` (pulse-echo: a period in depth is half a wavelength).  Outside :data:`FREQUENCY_MHZ` the axial
  spacing is wrong (units, or swapped).
* **lateral speckle against the period** -- the lateral speckle cell (FWHM of the envelope autocorrelation) is
  about the beam width, at least about half a wavelength (the diffraction limit), i.e. one axial RF period.
  Measured 4.8-13 periods on the data above (each envelope row minus its mean: a level that changes with depth
  only is the same in every line and would widen the cell); with the spacings exchanged the ratio falls by
  ``(dx / dy)^2`` to 0.04-0.29.  Below :data:`MIN_LATERAL_CELL_PERIODS` the spacing is swapped (or wrong).  A swap
  is seen when ``dx / dy`` is below 1 / sqrt(the ratio), 0.28-0.46 on these data.

* **speckle aspect of IQ data** -- IQ data remodulated to RF (:func:`femreg.io.iq.remodulate`) carry the carrier
  of the modulation frequency whatever the spacing given, so the two checks above cannot see exchanged spacings.
  The speckle can: a linear array's lateral speckle cell is wider than its axial one (lateral resolution is the
  coarser).  Lateral over axial cell (mm) measured 2.2-5.7 on the simulated 3-15 MHz probes' IQ and 2.8 on the
  in vivo frames' IQ, 0.13-0.42 with the spacings exchanged: below :data:`MIN_SPECKLE_ASPECT`, and above it once
  exchanged, the spacings are swapped (:func:`check_remodulated`).  benchmarks/iq_orientation.py: no false
  refusal on 66 IQ frames, exchanged spacings refused on 58 of them; missed where the IQ sample spacing is over
  half the line spacing (then the aspect's own spread, 2.2-5.7, covers the exchange's factor ``(dx / dy)^2``).
  An axial spacing several times too large narrows the aspect too (0.87 / 0.64 at 5 / 6 times a 5 MHz IQ's 0.077
  mm, past its 0.3 mm pitch): where the header states a sampling rate, the swap is named only if the exchanged
  axial value fits it (the IQ phases' decimation, else a whole decimation), else the spacing that fits is.

* **sign convention of IQ data** -- IQ demodulated with ``exp(+2 pi i f t)`` instead of ``exp(-2 pi i f t)``
  remodulates to an RF whose carrier moves *against* its envelope between frames: registered, it gives a wrong
  strain (a 1 % compression came out as 0.47 %, ``success=True``).  Two frames of moving tissue tell the conventions
  apart (:func:`femreg.io.iq.iq_convention`): on 30 simulated pairs (5 probes, 0.1-4 % compression, IQ decimated
  1x and 3x) and 8 in vivo pairs, each with both signs, every verdict was right (the wrong sign explained the
  phases at least 2.95 times worse), :func:`check_iq_sign`.  The same fit shows the demodulation frequency; given
  0.5 / 0.8 / 1.2 / 2 times the right one, 27 / 25 / 24 / 34 of the 38 pairs are refused (the 0.1 % pairs and some
  in vivo pairs have too little motion to tell), none with the right one.

* **speckle of envelope and B-mode frames** -- without a carrier the speckle cells (FWHM of the envelope
  autocorrelation, mm) are the spacing's witness: a probe's axial cell is about its pulse length, its lateral cell
  about its beam width, the wider of the two.  Cells outside :data:`ENVELOPE_CELL_MM` are a spacing in the wrong
  units (centimetres typed as mm make them 10 x too small); a lateral cell under :data:`ENVELOPE_MIN_ASPECT` of the
  axial one that exchanging the spacings makes plausible is a swap.  On the envelopes, log B-modes and resampled
  B-modes of the 3-15 MHz probes, the paper's and the in vivo frames (benchmarks/orientation_check.py, 45 pairs):
  no false refusal, exchanged spacings refused on 90 of 90, metres on 90 of 90; centimetres on 13 of 90, where the
  cells then fall under the bounds (the 12-15 MHz probes): on 3-7 MHz probes a spacing 10 x too small looks like
  a finer probe's (the mesh's margin then names the image's size in mm).

* **axial spacing against the file's header** -- none of the above sees an axial spacing off by a factor that
  keeps it plausible (a sampling rate typed 20 for 40 MHz, the factor 2 of the two-way travel left out): the
  strain is scale-free, the displacements and depths in mm are not.  Where the header states the RF sampling rate
  or the transmit frequency (:func:`femreg.io.checks.header_frequencies`), :func:`check_sampling` holds a given
  axial spacing against ``c / (2 fs)`` and the carrier against the transmit frequency (``read_frames`` runs it);
  without either, a carrier outside the clinical band :data:`TYPICAL_MHZ` is noted (:func:`frequency_note`,
  ``register``'s message).  benchmarks/spacing_check.py: 21 simulated references, no false refusal or note, 0.5 /
  2 / 2.7 / 1/2.7 / 10 / 0.1 times the spacing refused 21 of 21 each.

Only strong evidence refuses: smooth synthetic images and anything too small to measure pass.  ``register(..., check_orientation=False)``, ``track(...,
check_orientation=False)`` and the CLI's ``--no-orientation-check`` skip the check.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError, pass_as

__all__ = ["OrientationError", "OrientationReport", "carrier_ratio", "axial_carrier_ratio", "is_envelope", "diagnose",
           "check", "transposed_message", "exchanged_shape",
           "check_raw_shape", "check_remodulated", "check_iq_sign", "iq_decimation_from_phases", "iq_decimation", "FREQUENCY_MHZ", "MIN_SPECKLE_ASPECT",
           "CARRIER_RATIO", "NO_CARRIER_RATIO", "MIN_LATERAL_CELL_PERIODS", "SOUND_SPEED_M_S", "ENVELOPE_CELL_MM",
           "check_sampling", "frequency_note", "period_notes", "carrier_frequency", "SAMPLING_TOLERANCE",
           "TRANSMIT_RATIO", "TRANSMIT_NOTE_RATIO", "TYPICAL_MHZ"]

SOUND_SPEED_M_S = 1540.0
#: Plausible RF centre frequencies of medical ultrasound (MHz): abdominal probes to preclinical high frequency.
FREQUENCY_MHZ = (1.0, 60.0)
#: :func:`carrier_ratio` below this: a carrier (measured <= 0.027 on RF, >= 0.58 without a carrier).
CARRIER_RATIO = 0.1
#: :func:`carrier_ratio` above this: no carrier (between the two thresholds nothing is concluded).
NO_CARRIER_RATIO = 0.2
#: Lateral speckle cell / axial RF period below this is below the diffraction limit (measured 4.8-13 on correct
#: spacing, 0.04-0.29 with the spacings exchanged; each envelope row minus its mean, :func:`_lateral_cell`).
MIN_LATERAL_CELL_PERIODS = 1.0
#: The same ratio below this with one spacing value (square pixels): the line pitch taken for the axial sample
#: spacing (in vivo seq304 read so: 0.48, seq299: 0.72; correct spacings 4.8-13).
MIN_SQUARE_CELL_PERIODS = 2.0
#: Lateral / axial speckle cell (mm) of remodulated IQ data below this (and above it with the spacings exchanged):
#: the spacings are swapped (measured 2.2-5.7 correct, 0.13-0.42 exchanged).
MIN_SPECKLE_ASPECT = 1.0
#: Fewer samples (or lines) than this along an axis: its spectrum is not measured.
MIN_SAMPLES = 16
#: Spectra are zero-padded to at least this many bins, so that short axes still have a low band to measure.
MIN_FFT = 256
#: Rows of the block the speckle statistics are measured on (:func:`femreg.speckle.speckle_statistics`).
SPECKLE_ROWS = 1024
#: Plausible speckle cells (mm) of envelope and B-mode frames, ((axial min, max), (lateral min, max)): without a
#: carrier the spacing's only witness is the speckle's physical size (module docstring).  Measured 0.08-1.2 axially
#: and 0.2-3 laterally on envelopes, log B-modes and B-modes resampled to 0.05-0.1 mm pixels of the simulated
#: 3-15 MHz probes, up to 3.6 x 10.8 on the in vivo frames' B-mode (benchmarks/orientation_check.py); the lower
#: bounds leave room for 30-50 MHz preclinical probes (half a wavelength at 50 MHz is 0.015 mm).  A spacing in
#: centimetres taken for millimetres makes the cells 10 x too small, metres 1000 x.
ENVELOPE_CELL_MM = ((0.015, 10.0), (0.05, 50.0))
#: Lateral / axial speckle cell of an envelope or B-mode frame below this, and at least
#: :data:`ENVELOPE_SWAPPED_ASPECT` once the spacings are exchanged: the spacings are swapped (a linear array's
#: lateral resolution is the coarser; measured 1.0-4.7, the 1.0 on square 0.1 mm pixels where exchanging changes
#: nothing).
ENVELOPE_MIN_ASPECT = 0.7
ENVELOPE_SWAPPED_ASPECT = 1.4
#: Above this RF centre frequency (MHz) only preclinical probes remain, whose whole frames are at least about
#: 9 x 9 mm (30-70 MHz linear arrays).  A whole frame carrying a carrier above it yet smaller than
#: :data:`SMALL_FRAME_MM` is a clinical frame whose spacing was given in centimetres: all the other witnesses
#: (samples per period, speckle in periods) do not change with the units.
PRECLINICAL_MHZ = 20.0
#: (axial, lateral) extent in mm under which a whole frame above :data:`PRECLINICAL_MHZ` is refused; a 30-80 mm
#: deep, 25-50 mm wide clinical frame read in centimetres measures 3-8 x 2.5-5 mm.
SMALL_FRAME_MM = (8.0, 5.0)

#: A given axial spacing further than this (relative) from ``c / (2 fs)`` of the sampling rate the file's header
#: states is refused (:func:`check_sampling`): tissue's speed of sound, 1450-1600 m/s, moves ``c / (2 fs)`` by
#: up to 6 % from its value at 1540 m/s; the mistakes it is for are a factor 2 (two-way travel, 20 vs 40 MHz),
#: 2.7 or more (units, a wrong rate).
SAMPLING_TOLERANCE = 0.10
#: The RF carrier's frequency (:func:`carrier_frequency`) over the transmit frequency a header states: outside
#: this range the axial spacing is refused (:func:`check_sampling`).  Measured 0.977-1.077 on the simulated 3-15
#: MHz probes (benchmarks/spacing_check.py), which have no frequency-dependent attenuation: in tissue the centroid
#: falls below the transmit frequency with depth (to about 0.7 of it deep in the abdomen), and tissue harmonic
#: imaging receives at twice it.  An axial spacing 2.7 times too large or too small reads 0.36-0.40 or 2.6-2.9.
TRANSMIT_RATIO = (0.45, 2.5)
#: The same ratio outside this range, inside :data:`TRANSMIT_RATIO`: a note (a spacing 2 times off reads 0.49-0.54
#: or 1.95-2.15, as harmonic imaging or a strong downshift can).
TRANSMIT_NOTE_RATIO = (0.7, 1.45)
#: RF centre frequencies (MHz) of clinical probes' echoes: an implied carrier outside them, inside
#: :data:`FREQUENCY_MHZ`, gets a note (:func:`frequency_note`).  Measured 2.99-15.45 MHz on the simulated 3-15 MHz
#: probes and 4.52-4.65 MHz on the in vivo frames (benchmarks/spacing_check.py); abdominal and cardiac probes
#: transmit at 2-3.5 MHz, clinical linear arrays at up to 18 MHz, preclinical ones at 20-70 MHz.  An axial spacing
#: 2.7 times too large puts a 3-5 MHz probe below it, 2.7 times too small a 7.5-15 MHz probe above it.
TYPICAL_MHZ = (2.0, 20.0)

OVERRIDE = "check_orientation=False (CLI: --no-orientation-check)"


def _given(dx: float, dy: float, dz: tuple = ()) -> str:
    """The spacing a refusal judged, in the words of the caller (argument or flag; a volume's ``dz`` as typed)."""
    typed = " ".join(f"{v:g}" for v in (dx, dy, *dz))
    return pass_as(f"spacing (dx, dy) = ({dx:g}, {dy:g}) mm",
                   f"--spacing {typed} (axial, lateral{', elevational' if dz else ''} mm)")


def _pass_spacing(values: str, detail: str, lead: str = "spacing ", unit: str = "") -> str:
    """A spacing to pass, ``values`` as "a, b" mm: ``{lead}(a, b){unit} (detail; CLI: --spacing a b)`` from Python,
    ``--spacing a b (detail)`` on the command line (:func:`femreg.errors.pass_as`)."""
    flag = values.replace(",", "")
    return pass_as(f"{lead}({values}){unit} ({detail}; CLI: --spacing {flag})", f"--spacing {flag} ({detail})")


def override(python: str = OVERRIDE) -> str:
    """How a refusal names the way past the check: ``python`` (default :data:`OVERRIDE`), the flag alone on the
    command line."""
    return pass_as(python, "--no-orientation-check")


class OrientationError(InputError):
    """The frames look transposed, or their spacing swapped or implausible; the message says which and how to
    override the check.  ``problem``: "transposed", "swapped" or "spacing" (:class:`OrientationReport`), "shape" (a raw file read
    with its sizes exchanged), or ""
    when not known; ``report`` the :class:`OrientationReport` refused (from :func:`check`), else None."""

    def __init__(self, message: str = "", problem: str = "", report=None):
        super().__init__(message)
        self.problem = problem
        self.report = report


def _power_spectrum(img):
    """Line-averaged power spectrum along axis 0 (each line's mean removed) and its FFT length, zero-padded to a
    fast length of at least :data:`MIN_FFT` -- the spectrum of :func:`femreg.speckle.rf_period`."""
    from scipy import fft as sfft

    nf = sfft.next_fast_len(max(img.shape[0], MIN_FFT), real=True)
    P = np.mean(np.abs(sfft.rfft(img - img.mean(axis=0), n=nf, axis=0)) ** 2, axis=1)
    return P, nf


def carrier_ratio(image) -> float:
    """Mean power below a third of the spectral centroid over the mean power within a third of it (the band
    ``[2/3, 4/3]`` of the centroid), along axis 0 of a 2D image, DC left out.  Small (<< 1): a carrier along axis 0;
    ~1 or more: low-pass.  NaN where it cannot be measured (too few samples, no power)."""
    img = np.asarray(image, float)
    if img.ndim != 2 or img.shape[0] < MIN_SAMPLES or img.shape[1] < 2:
        return float("nan")
    P, nf = _power_spectrum(img)
    P[0] = 0.0
    f = np.fft.rfftfreq(nf)                         # cycles per sample
    total = float(np.sum(P))
    if not total > 0:
        return float("nan")
    fc = float(np.sum(f * P)) / total
    low = P[(f > 0) & (f < fc / 3.0)]
    band = P[(f > 2.0 * fc / 3.0) & (f < 4.0 * fc / 3.0)]
    if low.size == 0 or band.size == 0 or not np.mean(band) > 0:
        return float("nan")
    return float(np.mean(low) / np.mean(band))


def axial_carrier_ratio(frame) -> float:
    """:func:`carrier_ratio` along the depth of a frame (axial, lateral), on at most about 64 of its lines: the one
    carrier test of orientation checks, ``femreg info`` and the envelope test of :func:`is_envelope`."""
    frame = np.asarray(frame)
    return carrier_ratio(frame[:, ::max(1, frame.shape[1] // 64)])


def is_envelope(frame) -> bool:
    """True for a frame (axial, lateral) without an RF carrier along its depth (envelope, B-mode: the
    :func:`axial_carrier_ratio` above :data:`NO_CARRIER_RATIO`); False for RF and for frames too short to tell."""
    frame = np.asarray(frame)
    if frame.ndim != 2 or frame.shape[0] < MIN_SAMPLES:
        return False
    return bool(axial_carrier_ratio(frame) > NO_CARRIER_RATIO)


@dataclass
class OrientationReport:
    """What the RF says about its own layout.  ``carrier`` = :func:`carrier_ratio` along (axis 0, axis 1);
    ``period_mm`` the axial RF period (:func:`femreg.speckle.speckle_statistics`), ``samples_per_period``,
    ``frequency_mhz`` = c / (2 period), ``lateral_cell_mm`` the lateral speckle cell and ``cell_periods`` its
    ratio to the period (NaN where no carrier was found); ``axial_cell_mm`` the axial speckle cell of a frame
    without a carrier (envelope, B-mode; NaN otherwise); ``problem`` "" or "transposed", "swapped",
    "spacing"; ``message`` the reason (one line).  ``carrier_samples``: samples per RF period along axis 1 of a
    frame that looks transposed (NaN otherwise); ``sound_speed`` (m/s) and ``elevational`` (dz mm of a volume's
    central plane, or None) as :func:`diagnose` was given them; ``axial_given``: of a transposed frame for which
    both orders of the spacing give a plausible carrier, which given value the lateral speckle reads as the axial
    one ("axial": the first, "lateral": the second; None otherwise)."""

    spacing: tuple
    carrier: tuple
    period_mm: float = float("nan")
    samples_per_period: float = float("nan")
    frequency_mhz: float = float("nan")
    lateral_cell_mm: float = float("nan")
    cell_periods: float = float("nan")
    axial_cell_mm: float = float("nan")
    problem: str = ""
    message: str = ""
    small_frame: bool = False
    carrier_samples: float = float("nan")
    sound_speed: float = SOUND_SPEED_M_S
    elevational: float | None = None
    axial_given: str | None = None

    @property
    def has_carrier(self) -> bool:
        return bool(self.carrier[0] < CARRIER_RATIO)

    def summary(self) -> str:
        """One line for ``femreg info``."""
        if self.problem:
            return self.message
        if not self.has_carrier:
            cells = (f"; speckle cells {self.axial_cell_mm:.3g} x {self.lateral_cell_mm:.3g} mm (axial x lateral), "
                     "a plausible spacing" if np.isfinite(self.axial_cell_mm) else "")
            return (f"no RF carrier along axis 0 (low/centre band power {self.carrier[0]:.2g}): envelope or "
                    f"B-mode data, carrier checks skipped{cells}")
        return (f"RF carrier along axis 0: period {self.period_mm:.4g} mm ({self.samples_per_period:.1f} samples), "
                f"{self.frequency_mhz:.2f} MHz at {SOUND_SPEED_M_S:g} m/s; lateral speckle "
                f"{self.cell_periods:.1f} periods wide")


def diagnose(image, spacing, *, sound_speed: float = SOUND_SPEED_M_S,
             elevational: float | None = None, whole_frame: bool = False) -> OrientationReport:
    """Check one (axial, lateral) RF frame against ``spacing`` (dx, dy) mm (module docstring); never raises for
    the data (an image it cannot measure comes back without a problem).  ``elevational``: the elevational spacing
    dz (mm) when the frame is the central (axial, lateral) plane of a volume, so that the advice names the
    volume's transpose and its three spacings.  ``whole_frame``: the frame is one as the scanner wrote it (not a
    crop), so its size in mm is a witness too: above :data:`PRECLINICAL_MHZ` and smaller than
    :data:`SMALL_FRAME_MM` it is a spacing in centimetres (``small_frame`` True)."""
    from .speckle import speckle_statistics

    img = np.asarray(image, float)
    dx, dy = (float(s) for s in np.broadcast_to(np.asarray(spacing, float).ravel(), (2,)))
    if img.ndim != 2 or not np.all(np.isfinite(img)):
        return OrientationReport((dx, dy), (float("nan"), float("nan")))
    # spectra from a subset (at least 64 lines / 1024 rows) and the speckle from the strongest block of rows:
    # a few percent of a registration's time on a paper-size frame
    c0, c1 = _carrier_ratios(img)
    rep = OrientationReport((dx, dy), (c0, c1), sound_speed=sound_speed,
                            elevational=None if elevational is None else float(elevational))
    # the advice's spacings, as given and with axial and lateral exchanged, a volume's dz kept in third place
    dz = () if elevational is None else (float(elevational),)
    keep, swapped = (", ".join(f"{v:g}" for v in pair + dz) for pair in ((dx, dy), (dy, dx)))
    order = "axial, lateral, elevational" if dz else "axial, lateral"
    c_mm_us = sound_speed * 1e-3                     # m/s -> mm/us
    lo, hi = FREQUENCY_MHZ
    if _looks_transposed(c0, c1):
        rep.problem, rep.carrier_samples = "transposed", _centroid_samples(img.T)
        n1 = rep.carrier_samples
        if all(lo <= c_mm_us / (2.0 * n1 * v) <= hi for v in (dx, dy)):
            # both orders give a plausible carrier (a 12.5 MHz frame of 0.019 x 0.1 mm pixels: 12.4 or 2.4 MHz):
            # the lateral speckle, at least one RF period wide, says which; a units guess would be wrong here
            from .speckle import envelope

            lines = _lateral_cell(envelope(_strongest_rows(np.ascontiguousarray(img.T))), 1.0)
            keep_ok, swap_ok = (lines * b / (n1 * a) >= MIN_LATERAL_CELL_PERIODS for a, b in ((dx, dy), (dy, dx)))
            rep.axial_given = "lateral" if (swap_ok and not keep_ok) else "axial"
        rep.message = transposed_message(rep)
        return rep
    if not c0 < CARRIER_RATIO or img.shape[1] < 4:
        if c0 > NO_CARRIER_RATIO and min(img.shape) >= MIN_SAMPLES:
            _check_envelope(img, rep, keep, swapped, dz, order)
        return rep                                   # no carrier along axis 0: envelope / B-mode
    block = _strongest_rows(img)
    st = speckle_statistics(block, (dx, dy))
    rep.period_mm = float(st.period)
    rep.samples_per_period = rep.period_mm / dx
    rep.frequency_mhz = c_mm_us / (2.0 * rep.period_mm)
    rep.lateral_cell_mm = _lateral_cell(st.envelope, dy)
    rep.cell_periods = rep.lateral_cell_mm / rep.period_mm
    # with the spacings exchanged: the period scales by dy/dx, the lateral cell by dx/dy
    f_sw = rep.frequency_mhz * dx / dy
    cells_sw = rep.cell_periods * (dx / dy) ** 2
    swap_fits = lo <= f_sw <= hi and cells_sw >= MIN_LATERAL_CELL_PERIODS
    found = (f"RF period {rep.period_mm:.3g} mm ({rep.samples_per_period:.1f} samples, {rep.frequency_mhz:.2f} MHz "
             f"at {sound_speed:g} m/s), lateral speckle {rep.lateral_cell_mm:.3g} mm")
    if rep.cell_periods < MIN_LATERAL_CELL_PERIODS:
        rep.problem = "swapped" if swap_fits else "spacing"
        why = (f"{_given(dx, dy, dz)} gives an {found}, narrower than one axial RF period "
               f"({rep.cell_periods:.2f} of one), below the diffraction limit")
    elif not lo <= rep.frequency_mhz <= hi:
        rep.problem = "swapped" if swap_fits else "spacing"
        why = (f"axial spacing dx = {dx:g} mm gives an {found}: {rep.frequency_mhz:.3g} MHz is outside "
               f"{lo:g}-{hi:g} MHz")
    elif (whole_frame and rep.frequency_mhz > PRECLINICAL_MHZ and lo <= rep.frequency_mhz / 10.0 <= hi
          and img.shape[0] * dx < SMALL_FRAME_MM[0] and img.shape[1] * dy < SMALL_FRAME_MM[1]):
        rep.problem, rep.small_frame = "spacing", True
        why = (f"{_given(dx, dy, dz)} gives an {found} and a whole frame of only "
               f"{img.shape[0] * dx:.3g} x {img.shape[1] * dy:.3g} mm (axial x lateral): probes above "
               f"{PRECLINICAL_MHZ:g} MHz are preclinical ones, whose frames are larger than {SMALL_FRAME_MM[0]:g} x "
               f"{SMALL_FRAME_MM[1]:g} mm")
    else:
        return rep
    if rep.problem == "swapped":
        hint = "the axial and lateral spacings look swapped: pass " + _pass_spacing(
            swapped, f"{order}; {f_sw:.2f} MHz, lateral speckle {cells_sw:.1f} periods")
    else:
        # a uniform change of units leaves the speckle-to-period ratio alone and scales the frequency by 1 / k
        hint = _units_hint((dx, dy) + dz, order, ((1e3, "metres"), (1e-3, "micrometres"), (10.0, "centimetres")),
                           lambda k: (rep.problem == "spacing" and lo <= rep.frequency_mhz / k <= hi
                                      and rep.cell_periods >= MIN_LATERAL_CELL_PERIODS),
                           lambda k: f"{rep.frequency_mhz / k:.2f} MHz")
    rep.message = f"{why}; {hint}, or {override()}"
    return rep


def transposed_message(rep: OrientationReport, *, range_step: bool = False) -> str:
    """The refusal of a frame that looks transposed (``rep.problem == "transposed"``, from :func:`diagnose`): the
    transpose to apply and the spacing to pass, the axial one the one whose RF frequency is plausible along the
    carrier's axis (``rep.carrier_samples`` samples per period).  ``range_step``: the frame is a convex / sector
    frame in sample space (:mod:`femreg.geometry`) whose lateral value is the rays' distance at the middle sample,
    not one the user gave: the spacing to keep is the range step alone (``--spacing DR auto``)."""
    (dx, dy), (c0, c1), n1 = rep.spacing, rep.carrier, rep.carrier_samples
    dz = () if rep.elevational is None else (float(rep.elevational),)
    keep, swapped = (", ".join(f"{v:g}" for v in pair + dz) for pair in ((dx, dy), (dy, dx)))
    order = "axial, lateral, elevational" if dz else "axial, lateral"
    c_mm_us = rep.sound_speed * 1e-3                 # m/s -> mm/us
    lo, hi = FREQUENCY_MHZ
    if dz:
        what, shape, how = ("volumes", "(axial samples, lateral lines, elevational planes)",
                            "volume.transpose(1, 0, 2), volumes.transpose(0, 2, 1, 3)")
    else:
        what, shape, how = ("frames", "(axial samples, lateral lines)",
                            pass_as("frame.T, frames.transpose(0, 2, 1); read_frames(..., transpose=True); "
                                    "CLI: --transpose", "--transpose"))
    # which of the two given spacings is the axial one: the carrier's frequency says (users often give the
    # spacing as (axial, lateral) already while the array is stored lines-first)
    f_keep, f_swap = (c_mm_us / (2.0 * n1 * a) for a in (dx, dy))
    if rep.axial_given == "lateral":          # both plausible; the lateral speckle read the order (diagnose)
        f_keep = float("nan")
    elif rep.axial_given == "axial":
        f_swap = float("nan")
    if range_step:
        spacing_text = _range_step_text(dx, f_keep)
    elif lo <= f_keep <= hi and not lo <= f_swap <= hi:
        spacing_text = "keep " + _pass_spacing(keep, f"{order}; {f_keep:.2f} MHz", lead="the spacing ", unit=" mm")
    elif lo <= f_swap <= hi and not lo <= f_keep <= hi:
        spacing_text = "give the spacing in that order, " + _pass_spacing(
            swapped, f"{order}; {f_swap:.2f} MHz", lead="", unit=" mm")
    else:
        # neither order fits: a spacing in other units than mm (metres, as MATLAB exports store it) is
        # recognised by the order that fits once rescaled; exchanging it would make a wrong suggestion worse
        spacing_text = ""
        for k, unit in ((1e3, "metres"), (1e-3, "micrometres"), (10.0, "centimetres")):
            for vals, f in (((dx, dy), f_keep), ((dy, dx), f_swap)):
                if not spacing_text and lo <= f / k <= hi:
                    text = ", ".join(f"{v * k:.6g}" for v in vals + dz)
                    spacing_text = (f"pass the spacing in mm (its units look like {unit}), "
                                    + _pass_spacing(text, f"{order}; {f / k:.2f} MHz", lead=""))
        if not spacing_text:
            spacing_text = pass_as(f"give the spacing in that order, ({swapped}) mm",
                                   f"give the spacing in that order, --spacing {swapped.replace(',', '')}")
    return (f"the {what} look transposed: the RF carrier runs along axis 1 ({n1:.1f} samples per "
            f"period), axis 0 has none (low/centre band power {c0:.2g} vs {c1:.2g}); arrays must be "
            f"{shape}: transpose them ({how}) and {spacing_text}, or {override()}")


def _range_step_text(dr: float, f: float) -> str:
    """The spacing advice of a transposed convex / sector frame whose range step ``dr`` mm gives ``f`` MHz along
    the carrier: keep it, or the range step in mm when its units look like metres, micrometres or centimetres.
    Nothing is exchanged: the lateral value checked is the rays' distance, which the user did not give."""
    lo, hi = FREQUENCY_MHZ
    for k, unit in ((1.0, ""), (1e3, "metres"), (1e-3, "micrometres"), (10.0, "centimetres")):
        if lo <= f / k <= hi:
            v = f"{dr:g}" if k == 1.0 else f"{dr * k:.6g}"
            text = pass_as(f"the spacing {v} mm (range step; {f / k:.2f} MHz; CLI: --spacing {v} auto)",
                           f"--spacing {v} auto (range step; {f / k:.2f} MHz)")
            return "keep " + text if k == 1.0 else f"pass the range step in mm (its units look like {unit}), {text}"
    return (f"check the range step (the axial spacing, mm): {dr:g} mm gives {f:.3g} MHz, outside {lo:g}-{hi:g} "
            "MHz")


def _units_hint(spacing, order: str, units, fits, detail) -> str:
    """The advice for a spacing given in other units than mm: the first ``(k, unit)`` of ``units`` for which
    ``fits(k)`` (the data plausible with the spacing x k) names the unit and the spacing in mm (``spacing`` x k,
    ``detail(k)`` what it then gives); without one, to check the units and order."""
    for k, unit in units:
        if fits(k):
            text = ", ".join(f"{v * k:.6g}" for v in spacing)
            return f"the spacing's units look like {unit}: pass it in mm, " + _pass_spacing(
                text, f"{order}; {detail(k)}", lead="")
    return "check the spacing's units (mm) and order (axial, lateral)"


def _check_envelope(img, rep: OrientationReport, keep: str, swapped: str, dz: tuple, order: str) -> None:
    """The spacing check of a frame without a carrier (envelope, B-mode): its speckle cells (mm) against
    :data:`ENVELOPE_CELL_MM` (units) and their aspect against :data:`ENVELOPE_MIN_ASPECT` (swapped spacings);
    sets ``rep``'s cells, ``problem`` and ``message``."""
    from .speckle import speckle_statistics

    dx, dy = rep.spacing
    block = _signal_columns(_strongest_rows(img))
    if block is None:
        return
    cell = np.asarray(speckle_statistics(block, (dx, dy)).cell, float)
    rep.axial_cell_mm, rep.lateral_cell_mm = (float(c) for c in cell)
    if not np.all(np.isfinite(cell) & (cell > 0)):
        return
    (a0, a1), (l0, l1) = ENVELOPE_CELL_MM
    plausible = lambda c: a0 <= c[0] <= a1 and l0 <= c[1] <= l1  # noqa: E731
    found = (f"{_given(dx, dy, dz)} gives speckle cells of {cell[0]:.3g} mm axially and "
             f"{cell[1]:.3g} mm laterally")
    aspect = cell[1] / cell[0]
    cell_sw = cell * np.array([dy / dx, dx / dy])    # exchanged: the axial cell scales by dy/dx, the lateral by dx/dy
    aspect_sw = cell_sw[1] / cell_sw[0]
    if (aspect < ENVELOPE_MIN_ASPECT or not plausible(cell)) and plausible(cell_sw) \
            and aspect_sw >= ENVELOPE_SWAPPED_ASPECT:
        rep.problem = "swapped"
        rep.message = (f"{found}, the lateral cell {aspect:.2f} of the axial one, but a probe resolves depth "
                       f"better than across its lines; the axial and lateral spacings look swapped: pass "
                       + _pass_spacing(swapped, f"{order}; cells {cell_sw[0]:.3g} x {cell_sw[1]:.3g} mm")
                       + f", or {override()}")
    elif not plausible(cell):
        rep.problem = "spacing"
        # a uniform change of units scales both cells by k
        hint = _units_hint((dx, dy) + dz, order, ((10.0, "centimetres"), (1e3, "metres"), (1e-3, "micrometres")),
                           lambda k: plausible(cell * k), lambda k: f"cells {cell[0] * k:.3g} x {cell[1] * k:.3g} mm")
        rep.message = (f"{found}, outside what ultrasound probes resolve ({a0:g}-{a1:g} mm axially, {l0:g}-{l1:g} "
                       f"mm laterally); {hint}, or {override()}")


def _signal_columns(block):
    """The columns of ``block`` without fill (:func:`femreg.echo.fill_level`: the black wedges of a
    scan-converted convex or sector image, a blanked margin), whose edges would otherwise set the
    speckle cell (13 mm axially on a fan-masked L12 B-mode); None when fewer than :data:`MIN_SAMPLES` columns
    remain (nothing measured)."""
    from .echo import fill_level

    v = fill_level(block)
    if v is not None:
        keep = ~np.any(block == v, axis=0)
        # the longest run of kept columns: the autocorrelation needs neighbouring lines
        best, start, run = (0, 0), 0, 0
        for j, ok in enumerate(np.r_[keep, False]):
            if ok:
                run += 1
            else:
                if run > best[1] - best[0]:
                    best = (start, start + run)
                start, run = j + 1, 0
        block = block[:, best[0]:best[1]]
    return block if block.shape[1] >= MIN_SAMPLES and block.shape[0] >= MIN_SAMPLES else None


def _strongest_rows(img, n: int = SPECKLE_ROWS):
    """The block of ``n`` consecutive rows with the largest mean square (the whole image when it is shorter):
    where the echo is, not a noise floor at depth."""
    m = img.shape[0]
    if m <= n:
        return img
    starts = np.arange(0, m - n + 1, n // 2)
    power = [float(np.mean(img[s:s + n] ** 2)) for s in starts]
    s = int(starts[int(np.argmax(power))])
    return img[s:s + n]


def _lateral_cell(env, dy: float) -> float:
    """Lateral speckle cell (mm, FWHM of the envelope autocorrelation across lines) of an envelope block
    (n_rows, n_lines), each row minus its own mean first (not divided by its spread: rows of noise below the
    floor, one line wide, would then weigh as much as the echo).  A level that changes with depth
    alone (attenuation without time-gain compensation, a bright skin line over hypoechoic fat) is the same in
    every line: left in, it correlates the lines over the whole width (a 12.5 MHz frame with 0.35 mm beam read
    6 mm, 97 RF periods; swapped still 3.6, above the limit of 1, so the swap passed)."""
    from .speckle import _envelope_cell

    e = np.asarray(env, float)
    e = e - e.mean(axis=1, keepdims=True)
    return float(_envelope_cell(np.ascontiguousarray(e.T), 0, dy))


def _carrier_ratios(img) -> tuple:
    """(along axis 0, along axis 1) carrier ratios of a frame (:func:`axial_carrier_ratio`, :func:`carrier_ratio`
    of at most about 1024 of its rows)."""
    img = np.asarray(img, float)
    return axial_carrier_ratio(img), carrier_ratio(img[::max(1, img.shape[0] // 1024)].T)


def _looks_transposed(c0: float, c1: float) -> bool:
    """The carrier runs along the lines (axis 1) and not along the depth (axis 0): frames stored lines first."""
    return c1 < CARRIER_RATIO and c0 > NO_CARRIER_RATIO


def _centroid_samples(img) -> float:
    """1 / spectral centroid along axis 0 in samples (:func:`femreg.speckle.rf_period` with unit spacing)."""
    from .speckle import rf_period

    return float(rf_period(img, (1.0, 1.0)))


def check(image, spacing, *, sound_speed: float = SOUND_SPEED_M_S,
          elevational: float | None = None, whole_frame: bool = False, one_value: bool = False) -> OrientationReport:
    """:func:`diagnose`, raising :class:`OrientationError` (an :class:`InputError`) with its message when the
    frame looks transposed or its spacing swapped or implausible.  ``one_value``: the spacing was given as one
    number (square pixels), refused too when its lateral speckle is narrower than
    :data:`MIN_SQUARE_CELL_PERIODS` axial RF periods -- RF lines are rarely as close as the axial samples.  The
    error carries the report (``report``), from which a caller that knows the frame's kind words it anew
    (:func:`transposed_message`)."""
    rep = diagnose(image, spacing, sound_speed=sound_speed, elevational=elevational, whole_frame=whole_frame)
    square = (one_value and np.isfinite(rep.cell_periods) and rep.cell_periods < MIN_SQUARE_CELL_PERIODS
              and FREQUENCY_MHZ[0] <= rep.frequency_mhz <= FREQUENCY_MHZ[1] and not rep.small_frame)
    if rep.problem and not (square and rep.problem != "transposed"):
        raise OrientationError(rep.message, problem=rep.problem, report=rep)
    if square:     # one value: the line pitch is missing, which says more than "narrower than a period"
        dx = float(np.ravel(spacing)[0])
        raise OrientationError(
            f"spacing {dx:g} (one value) means square pixels, {dx:g} x {dx:g} mm: the lateral speckle is then "
            f"{rep.lateral_cell_mm:.3g} mm, {rep.cell_periods:.2g} axial RF periods, narrower than a wavelength (2 "
            f"periods) -- RF lines are rarely as close as the axial samples; give both, "
            + pass_as(f"spacing=({dx:g}, DY) (axial sample spacing, lateral line pitch in mm; CLI: --spacing {dx:g} "
                      "DY)", f"--spacing {dx:g} DY (axial sample spacing, lateral line pitch in mm)")
            + f", or {override()}", problem="spacing")
    return rep


def carrier_frequency(frame, dx: float, sound_speed: float = SOUND_SPEED_M_S) -> float:
    """The RF centre frequency (MHz) the carrier along the depth of ``frame`` (axial, lateral) reads at axial
    spacing ``dx`` mm: ``c / (2 T)`` with ``T`` the spectral-centroid period (:func:`femreg.speckle.rf_period`) of
    at most about 64 of its lines; NaN without a carrier (envelope, B-mode: :func:`axial_carrier_ratio` not below
    :data:`CARRIER_RATIO`) or too few samples to tell."""
    img = np.asarray(frame, float)
    if img.ndim != 2 or img.shape[0] < MIN_SAMPLES or not axial_carrier_ratio(img) < CARRIER_RATIO:
        return float("nan")
    n = _centroid_samples(img[:, ::max(1, img.shape[1] // 64)])
    return float(sound_speed * 1e-3 / (2.0 * n * float(dx))) if np.isfinite(n) and n > 0 else float("nan")


def frequency_note(f_mhz: float) -> str:
    """A note for an RF carrier that reads ``f_mhz`` MHz at the axial spacing given, outside :data:`TYPICAL_MHZ`
    but inside :data:`FREQUENCY_MHZ` (outside that :func:`diagnose` refuses it): the likely mistakes in the
    spacing; "" inside the typical range or when not measured.  Only a note: low-frequency and preclinical probes
    read so."""
    lo, hi = TYPICAL_MHZ
    if not (np.isfinite(f_mhz) and FREQUENCY_MHZ[0] <= f_mhz <= FREQUENCY_MHZ[1]) or lo <= f_mhz <= hi:
        return ""
    if f_mhz < lo:
        why = ("if the probe is not a low-frequency one the axial spacing is too large (c / (2 fs): a sampling rate "
               "taken too low, e.g. 20 for 40 MHz, or the factor 2 of the two-way travel left out)")
    else:
        why = ("if the probe is not a preclinical high-frequency one the axial spacing is too small (c / (2 fs): a "
               "sampling rate taken too high, e.g. 40 for 20 MHz, or the factor 2 counted twice)")
    return (f"the RF carrier reads {f_mhz:.3g} MHz at the axial spacing given, outside the {lo:g}-{hi:g} MHz of "
            f"clinical probes: {why}; displacements and depths in mm scale with it")


def period_notes(frame, period_mm) -> list:
    """``[frequency_note]`` for a frame (axial, lateral) with a carrier whose RF period (mm, at the axial spacing
    given; None where not measured) implies a frequency outside :data:`TYPICAL_MHZ`, else []: the note register
    adds to its message."""
    if period_mm is None or not (np.isfinite(period_mm) and period_mm > 0) \
            or not axial_carrier_ratio(frame) < CARRIER_RATIO:
        return []
    note = frequency_note(SOUND_SPEED_M_S * 1e-3 / (2.0 * float(period_mm)))
    return [note] if note else []


#: Line pitches (mm) of linear arrays, 0.05-0.5 mm on the simulated probes, with room: which value of a spacing
#: in other units than mm is a pitch once converted (:func:`check_sampling`).
LINE_PITCH_MM = (0.01, 5.0)


def _pitch_plausible(dy: float) -> bool:
    return LINE_PITCH_MM[0] <= dy <= LINE_PITCH_MM[1]


def _sampling_mistake(ratio: float, c: float) -> str:
    """The likely mistake behind an axial spacing ``ratio`` times ``c / (2 fs)``, in words ("" for none)."""
    for k, text in ((2.0, "twice c / (2 fs): the factor 2 of the two-way travel left out (c / fs), or half the "
                          "sampling rate"),
                    (0.5, "half c / (2 fs): twice the sampling rate, or the factor 2 counted twice"),
                    (1e3, "1000 times c / (2 fs): micrometres taken for mm"),
                    (1e-3, "1/1000 of c / (2 fs): metres taken for mm"),
                    (10.0, "10 times c / (2 fs): a sampling rate a decade off, or a unit slip"),
                    (0.1, "1/10 of c / (2 fs): centimetres taken for mm, or a sampling rate a decade off")):
        if abs(ratio / k - 1.0) <= SAMPLING_TOLERANCE:
            return text
    return (f"{ratio:.3g} times c / (2 fs): a sampling rate other than the header's, or a speed of sound of "
            f"{c * ratio:.0f} m/s, which no soft tissue has")


#: Whole decimations of the sampling rate an IQ sample spacing is taken for (:func:`iq_decimation`), and how close
#: to one the spacing must be (relative).
IQ_DECIMATIONS = range(1, 17)
IQ_DECIMATION_TOLERANCE = 0.02


def iq_decimation(dx_iq: float, dx_fs: float):
    """The whole decimation ``q`` (:data:`IQ_DECIMATIONS`) with ``dx_iq`` within :data:`IQ_DECIMATION_TOLERANCE`
    of ``q dx_fs``, else None."""
    ratio = dx_iq / dx_fs
    q = int(round(ratio))
    return q if q in IQ_DECIMATIONS and abs(ratio / q - 1.0) <= IQ_DECIMATION_TOLERANCE else None


#: How far (relative) a given demodulation frequency may lie from the one the file states.
IQ_FREQUENCY_TOLERANCE = 0.02


def _iq_sampling_notes(iq: dict, known: dict, sound_speed, where: str, spacing_given: bool = True,
                       override_as: str = OVERRIDE) -> list:
    """The IQ part of :func:`check_sampling`.  A demodulation frequency given more than
    :data:`IQ_FREQUENCY_TOLERANCE` from the one the header states is refused (problem "iq-frequency"): with
    another frequency the strain comes out scaled, or, at a spacing off by the same factor, every depth and
    displacement.  A given IQ sample spacing is held against the sampling rate the header states: IQ is usually
    decimated after sampling, so a whole multiple ``q`` of ``c / (2 fs)`` is what the data can have (no note);
    any other value is noted as unlike the header, not refused, since beamformers also write IQ onto grids
    of their own.  A spacing wrong by a factor shows in the IQ phases between moving frames, which
    :func:`check_iq_sign` refuses naming the spacing they fit."""
    f = iq.get("modulation_frequency_mhz")
    if "demod_mhz" in known and f is not None:
        fd, d_words = known["demod_mhz"]
        if abs(float(f) / fd - 1.0) > IQ_FREQUENCY_TOLERANCE:
            raise OrientationError(
                f"{where}" + pass_as(f"modulation_frequency {float(f):g} MHz", f"--iq-frequency {float(f):g} MHz")
                + f" given, but the file states the demodulation frequency {fd:g} MHz ({d_words}): remodulated at "
                f"another frequency the strain comes out scaled by about their ratio (or, with the axial spacing off "
                f"by the same factor, every depth and displacement); pass "
                + pass_as(f"modulation_frequency={fd:.6g} (CLI: --iq-frequency {fd:.6g})", f"--iq-frequency {fd:.6g}")
                + f", or {override(override_as)} to use the value given", problem="iq-frequency")
    if not spacing_given or "fs_mhz" not in known or "iq_spacing_mm" not in iq:
        return []
    fs, words = known["fs_mhz"]
    c = float(sound_speed if sound_speed is not None else iq.get("sound_speed", SOUND_SPEED_M_S))
    dx_fs = c * 1e-3 / (2.0 * fs)
    dx = float(iq["iq_spacing_mm"])
    q = iq_decimation(dx, dx_fs)
    said = (f"the IQ sample spacing {dx:g} mm given is {dx / dx_fs:.3g} times c / (2 fs) = {dx_fs:.5g} mm of the "
            f"sampling rate the file states, {fs:g} MHz ({words}; c = {c:g} m/s)")
    if q is not None:
        return []           # IQ decimated q times after sampling: what such data have, no note
    whole = max(1, int(round(dx / dx_fs)))
    return [f"{where}{said}, no whole decimation of it (IQ decimated q times after sampling has q x {dx_fs:.5g} "
            f"mm, e.g. {whole * dx_fs:.5g}): unless the beamformer wrote the IQ onto a grid of its own, the axial "
            f"spacing is off and every depth and displacement with it"]


def check_sampling(frames, spacing=None, *, sound_speed=None, where: str = "", elevational=None,
                   override_as: str = OVERRIDE) -> list:
    """Hold the axial spacing of :class:`femreg.io.Frames` against what the file's header states about the RF
    (:func:`femreg.io.checks.header_frequencies`); returns notes (a list of strings), raises
    :class:`OrientationError` (problem "sampling") for a clear contradiction:

    * a sampling rate ``fs``: an axial value given in ``spacing`` (the user's, not the file's) further than
      :data:`SAMPLING_TOLERANCE` from ``c / (2 fs)`` is refused, naming both and the value to pass;
    * a transmit frequency: the carrier the frames read at their axial spacing (:func:`carrier_frequency`) over
      it outside :data:`TRANSMIT_RATIO` is refused, outside :data:`TRANSMIT_NOTE_RATIO` noted.

    ``sound_speed`` (m/s): the one given (else the header's, else 1540).  IQ data (``metadata["iq"]``: the carrier
    is the demodulation frequency's whatever the spacing; their own checks, :func:`check_iq_sign`), frames that
    look transposed (:func:`diagnose` names their spacing with the transpose) and, for the transmit check, frames
    without a carrier are skipped.  ``elevational``: a volume's plane spacing (mm), kept in third place in the
    spacing a refusal names; ``override_as``: the Python argument that skips the check (the CLI's flag is
    ``--no-orientation-check`` either way)."""
    from .io.checks import check_spacing, header_frequencies

    meta = dict(frames.metadata or {})
    known = header_frequencies(meta)
    if "iq" in meta and known:
        return _iq_sampling_notes(meta["iq"], known, sound_speed, where, spacing is not None, override_as)
    if "iq" in meta or not known or frames.spacing is None:
        return []
    img = np.asarray(frames.frames[0])
    if img.ndim == 2 and min(img.shape) >= MIN_SAMPLES and _looks_transposed(*_carrier_ratios(img)):
        return []       # transposed: that refusal (diagnose) names the spacing along with the transpose
    c = float(sound_speed) if sound_speed is not None else float(known.get("sound_speed", (SOUND_SPEED_M_S,))[0])
    c_words = f"c = {c:g} m/s" + ("" if sound_speed is not None or "sound_speed" in known else " assumed")
    dx, dy = (float(v) for v in np.ravel(frames.spacing)[:2])
    typed, typed_y = (None, None) if spacing is None else check_spacing(spacing, allow_none=True)
    notes, nlo, nhi = [], *TRANSMIT_NOTE_RATIO
    f = float("nan")                                # the carrier at the axial spacing the frames carry
    if "transmit_mhz" in known:
        ft, t_words = known["transmit_mhz"]
        f = carrier_frequency(np.asarray(frames.frames[0]), dx, c)
    if "fs_mhz" in known and typed is not None:
        fs, words = known["fs_mhz"]
        dx_h = c * 1e-3 / (2.0 * fs)               # m/s -> mm/us over MHz: mm
        ratio = typed / dx_h
        swapped = typed_y is not None and abs(typed_y / dx_h - 1.0) <= SAMPLING_TOLERANCE
        said = (f"the axial spacing {typed:g} mm given implies {c * 1e-3 / (2.0 * typed):.4g} MHz sampling at "
                f"{c_words}, but the file states {fs:g} MHz ({words}): the axial spacing c / (2 fs) is {dx_h:.5g} mm")
        if abs(ratio - 1.0) <= SAMPLING_TOLERANCE or swapped:       # a swap: the orientation checks name it
            pass
        elif np.isfinite(f) and nlo <= f / ft <= nhi:
            # the carrier at the given spacing is the transmit frequency's: the header's rate is not the samples'
            # (frames decimated after sampling, the rate before it kept)
            notes.append(f"{where}{said}; the RF carrier at the spacing given reads {f:.3g} MHz, as the transmit "
                         f"frequency ({ft:g} MHz, {t_words}): the value given is used, the header's rate taken for "
                         "one before decimation")
        else:
            # a spacing in other units: the line pitch too, where only that makes it a pitch (LINE_PITCH_MM)
            k = next((k for k in (1e3, 1e-3, 10.0, 0.1) if abs(ratio / k - 1.0) <= SAMPLING_TOLERANCE), 1.0)
            y = dy / k if not _pitch_plausible(dy) and _pitch_plausible(dy / k) else dy
            z = () if elevational is None else (f"{float(elevational):g}",)
            fix = pass_as(f"spacing=({', '.join((f'{dx_h:.5g}', f'{y:.6g}') + z)})",
                          f"--spacing {' '.join((f'{dx_h:.5g}', f'{y:.6g}') + z)}")
            order = "axial, lateral, elevational" if z else "axial, lateral"
            m = round(ratio)
            kept = (f"; frames decimated after sampling (one sample in {m} kept) have {m} times the header's "
                    "spacing: then use the value given" if 2 <= m <= 8 and abs(ratio / m - 1.0) <= 0.02 else "")
            raise OrientationError(
                f"{where}{said}, and {typed:g} is {_sampling_mistake(ratio, c)}; pass {fix} ({order} mm)"
                f"{kept}, or {override(override_as)} to use the value given", problem="sampling")
    if "transmit_mhz" in known:
        if not np.isfinite(f) or notes:
            return notes
        r = f / ft
        if not nlo <= r <= nhi and nlo <= r * dx / dy <= nhi:
            return notes                # the spacings exchanged fit: a swap, which the orientation checks name
        found = (f"the RF carrier reads {f:.3g} MHz at the axial spacing {dx:g} mm ({c_words}), {r:.2f} times the "
                 f"transmit frequency the file states, {ft:g} MHz ({t_words})")
        cure = (f"an axial spacing of {dx * r:.4g} mm would put the carrier at {ft:g} MHz; the axial spacing is "
                "c / (2 fs), fs the RF sampling rate")
        lo, hi = TRANSMIT_RATIO
        if not lo <= r <= hi:
            raise OrientationError(
                f"{where}{found}: outside the {lo:g}-{hi:g} times that attenuation and harmonic imaging explain, "
                f"so the axial spacing looks wrong ({cure}); check it, or {override(override_as)}", problem="sampling")
        if not nlo <= r <= nhi:
            also = " (tissue harmonic imaging receives at twice the transmit frequency)" if r > nhi else \
                " (attenuation lowers the carrier with depth, though rarely this far)"
            notes.append(f"{where}{found}{also}: if the frames are not so, the axial spacing is off by about that "
                         f"factor ({cure})")
    return notes


def transposed_as_told(message: str, where: str = "") -> str:
    """A refusal of frames that look transposed once ``--transpose`` was applied, reworded: they were stored the
    right way round, so the advice is to leave the flag out (``where``: for which recording, e.g. its settings
    file), not to pass it."""
    return message.replace("transpose them (--transpose)",
                           "leave out --transpose" + (f" {where}" if where else "")
                           + " (the file stores them samples first, as femreg reads them)")


def exchanged_shape(frame) -> str:
    """Advice when a raw (headerless) frame was read with its two sizes exchanged, else "".

    Read with its sizes exchanged a raw frame is scrambled, not transposed: no carrier on either axis, so
    :func:`diagnose` takes it for envelope data.  When the same samples in file order, read the other way round,
    carry one along axis 0, the ``--shape`` (``shape=``) given was the wrong way round."""
    n0, n1 = np.shape(frame)
    if axial_carrier_ratio(frame) < CARRIER_RATIO:
        return ""                                   # a carrier as read: not scrambled
    alt = np.asarray(frame).reshape(n1, n0)        # the same samples in file order, the sizes exchanged
    if not axial_carrier_ratio(alt) < CARRIER_RATIO:
        return ""
    return (f"no RF carrier when read as {n0} x {n1}, but one along axis 0 when read as {n1} x {n0}: the "
            + pass_as(f"shape looks exchanged, pass shape=({n1}, {n0}) (axial, lateral: samples per line, then "
                      f"lines; CLI: --shape {n1} {n0})",
                      f"--shape looks exchanged, pass --shape {n1} {n0} (AXIAL LATERAL: samples per line, then lines)"))


def check_raw_shape(frames) -> None:
    """Refuse :class:`femreg.io.Frames` read from a raw file (or a folder of them) with their two sizes exchanged
    (:func:`exchanged_shape`): :class:`OrientationError` naming the shape to pass.  Other formats carry their
    shape in the file and pass."""
    if "raw" not in str(dict(frames.metadata).get("format", "")):
        return
    msg = exchanged_shape(frames.frames[0])
    if msg:
        raise OrientationError(f"{msg}; or {override()}", problem="shape")


def check_remodulated(frames) -> None:
    """Refuse :class:`femreg.io.Frames` remodulated from IQ data (``metadata["iq"]``) whose spacings look exchanged
    (module docstring, speckle aspect): :class:`OrientationError` naming the spacing to pass.  Frames that were
    not IQ, or too small to measure, pass."""
    iq = dict(frames.metadata).get("iq")
    img = np.asarray(frames.frames[0], float)
    if not iq or min(img.shape) < MIN_SAMPLES:
        return
    from .speckle import speckle_statistics

    st = speckle_statistics(_strongest_rows(img), frames.spacing)
    ax, lat = (float(c) for c in st.cell)
    if not (np.isfinite(ax) and np.isfinite(lat) and ax > 0 and lat > 0):
        return
    dx, dy = float(iq["iq_spacing_mm"]), float(frames.spacing[1])
    aspect = lat / ax
    swapped = aspect * (dx / dy) ** 2
    if aspect >= MIN_SPECKLE_ASPECT or swapped < MIN_SPECKLE_ASPECT:
        return
    found = (f"IQ data read with spacing ({dx:g}, {dy:g}) mm: the lateral speckle ({lat:.3g} mm) is narrower than "
             f"the axial ({ax:.3g} mm), {aspect:.2f} of it, while a linear array's lateral resolution is the coarser")
    header = _iq_header_step(frames)
    if header is not None:
        # an axial spacing several times too large (0.37 mm for 0.074) narrows the speckle's aspect as a swap
        # does: exchange the spacings only where the header's sampling rate and the IQ phases agree with it
        _refuse_unlike_header(frames, found, dx, dy, *header)
    raise OrientationError(
        f"{found}; the axial and lateral spacings look swapped: pass "
        + _pass_spacing(f"{dy:g}, {dx:g}", "axial IQ sample spacing, then line spacing; lateral / axial speckle "
                        f"{swapped:.1f}")
        + f", or {override()}",
        problem="swapped")


def _decimation_words(q: int) -> str:
    """How an IQ axial step of ``q`` times ``c / (2 fs)`` is named in a refusal."""
    return "c / (2 fs)" if q == 1 else f"{q} x c / (2 fs), IQ decimated {q}x after sampling"


def _iq_header_step(frames):
    """``(dx_fs mm, fs MHz, words, c m/s)``: the axial step ``c / (2 fs)`` of the sampling rate the header of IQ
    :class:`femreg.io.Frames` states, else None."""
    from .io.checks import header_frequencies

    meta = dict(frames.metadata or {})
    known = header_frequencies(meta)
    if "fs_mhz" not in known:
        return None
    fs, words = known["fs_mhz"]
    c = float(meta["iq"].get("sound_speed", SOUND_SPEED_M_S))
    return c * 1e-3 / (2.0 * fs), fs, words, c


def _refuse_unlike_header(frames, found: str, dx: float, dy: float, dx_fs: float, fs: float, words: str,
                          c: float) -> None:
    """Part of :func:`check_remodulated` for IQ whose header states a sampling rate (axial step ``dx_fs`` mm):
    returns (the swap is named) where the exchanged axial value ``dy`` fits it, raises :class:`OrientationError`
    (problem "iq-spacing") naming the spacing that does where it does not.  The IQ phases between frames 0 and 1
    (:func:`iq_decimation_from_phases`) give the decimation ``q`` (1-4), hence the axial step ``q dx_fs``; without
    them, ``dy`` must be a whole decimation (:func:`iq_decimation`) of ``dx_fs``."""
    from .io.iq import baseband

    iq = dict(frames.metadata)["iq"]
    f = float(iq["modulation_frequency_mhz"])
    q = None
    if frames.n_frames >= 2:
        up = max(1, int(iq.get("upsampled", 1)))
        dz = float(frames.spacing[0])
        # back to the stored IQ samples (standard sign: the remodulation applied the convention given)
        pair = [baseband(np.asarray(frames.frames[i], float), dz, f, sound_speed=c, axis=0)[::up] for i in (0, 1)]
        try:
            q = iq_decimation_from_phases(pair[0], pair[1], dx_fs, f, c)
        except ValueError:
            q = None
    if q is not None:
        if abs(dy / (q * dx_fs) - 1.0) <= SAMPLING_TOLERANCE:
            return
        right = q * dx_fs
        how = _decimation_words(q)
        k = dx / right
        off = f"{k:.3g} times too large" if k > 1 else f"{1 / k:.3g} times too small"
        raise OrientationError(
            f"{found}; exchanged, the axial spacing {dy:g} mm would be {dy / dx_fs:.3g} times c / (2 fs) = "
            f"{dx_fs:.5g} mm of the sampling rate the file states, {fs:g} MHz ({words}; c = {c:g} m/s), while the "
            f"IQ phases between the frames turn as for {how}: the axial spacing {dx:g} mm looks {off}, not "
            f"swapped; pass " + _pass_spacing(f"{right:.5g}, {dy:g}", f"{how}, axial IQ sample spacing, then line "
                                              "spacing") + f", or {override()}", problem="iq-spacing")
    if iq_decimation(dy, dx_fs) is not None:
        return
    raise OrientationError(
        f"{found}; but exchanged, the axial spacing {dy:g} mm would be {dy / dx_fs:.3g} times c / (2 fs) = "
        f"{dx_fs:.5g} mm of the sampling rate the file states, {fs:g} MHz ({words}; c = {c:g} m/s), no whole "
        f"decimation of it, and the given {dx:g} mm is {dx / dx_fs:.3g} times it: the axial spacing looks off (IQ "
        f"decimated q times after sampling has q x {dx_fs:.5g} mm, e.g. {2 * dx_fs:.5g} for q = 2); check it, "
        f"or {override()}", problem="iq-spacing")


def _iq_spacing_fix(iq: dict, spacing, f: float, fb: float, metadata, c: float) -> tuple:
    """``(axial spacing mm, words)`` at which IQ phases that turn as for ``fb`` MHz (:func:`iq_convention`) fit the
    ``f`` MHz given: the phase per sample is ``4 pi f dx / c``, so a spacing ``k`` times too large reads as ``f /
    k``.  Rounded to a whole decimation of the header's sampling rate (:func:`iq_decimation`) where one is within
    10 %; ``(None, "")`` for the other sign."""
    from .io.checks import header_frequencies

    if fb <= 0:
        return None, ""
    dx_iq = float(iq.get("iq_spacing_mm", spacing[0]))
    dx = dx_iq * fb / f
    known = header_frequencies(metadata)
    if "fs_mhz" in known:
        fs, words = known["fs_mhz"]
        dx_fs = c * 1e-3 / (2.0 * fs)
        q = int(round(dx / dx_fs))
        if q in IQ_DECIMATIONS and abs(dx / (q * dx_fs) - 1.0) <= SAMPLING_TOLERANCE:
            how = _decimation_words(q)
            return q * dx_fs, f"{how}, with fs = {fs:g} MHz ({words}) and c = {c:g} m/s"
    return dx, f"the spacing at which the phases fit {f:g} MHz"


def iq_decimation_from_phases(iq_a, iq_b, dx_fs: float, f: float, sound_speed: float = SOUND_SPEED_M_S):
    """The whole decimation ``q`` (1 to 4) of IQ frames ``(axial, lateral)`` demodulated at ``f`` MHz whose header
    states a sampling rate of axial step ``dx_fs`` mm (``c / (2 fs)``), from the IQ phases between the two frames
    (:func:`femreg.io.iq.iq_convention`, as :func:`check_iq_sign` reads them: remodulated at ``dx_fs``, back to
    baseband): at a step ``q`` times too small they turn as for ``q f``.  None when they cannot tell (too little
    motion or correlation, the other sign, no whole ``q`` within :data:`SAMPLING_TOLERANCE`)."""
    from .io.iq import baseband, iq_convention, remodulate

    c = float(sound_speed)
    rf = [remodulate(np.asarray(x), dx_fs, f, sound_speed=c, axis=0) for x in (iq_a, iq_b)]
    dz = rf[0][1]
    a, b = (baseband(r[0], dz, f, sound_speed=c, axis=0) for r in rf)
    verdict, _, _, fb = iq_convention(a, b, dz, f, sound_speed=c)
    if verdict == "standard":
        return 1
    if verdict != "frequency" or fb <= 0:
        return None
    q = int(round(fb / f))
    return q if 2 <= q <= 4 and abs(fb / (q * f) - 1.0) <= SAMPLING_TOLERANCE else None


def check_iq_sign(frame_a, frame_b, spacing, iq: dict, *, where: str = "", metadata=None) -> tuple:
    """Refuse two RF frames remodulated from IQ data (``iq``: the ``metadata["iq"]`` record of
    :func:`femreg.io.read_frames`) whose carrier moves against the envelope (module docstring, sign convention),
    or whose phase turns as for another demodulation frequency than the one given: :class:`OrientationError`
    naming ``--iq-conjugate`` (problem "iq-sign") or the frequency the phases show ("iq-frequency").  Returns
    :func:`femreg.io.iq.iq_convention`'s verdict (``"unknown"`` passes: too little motion or correlation to tell).

    An axial spacing ``k`` times off turns the phases as for ``f / k`` (the phase per sample is ``4 pi f dx / c``):
    the refusal names the spacing at which they fit the frequency given too (:func:`_iq_spacing_fix`), first where
    that frequency is the demodulation frequency the header (``metadata``, the frames') states.

    The RF goes back to baseband on its own (upsampled) grid rather than using the IQ as stored: on the in vivo
    frames decimated to 0.08 mm the phases then show 4.26 MHz for the true 4.16 (4.70 from the stored IQ)."""
    from .io.iq import baseband, iq_convention

    f, c = float(iq["modulation_frequency_mhz"]), float(iq.get("sound_speed", SOUND_SPEED_M_S))
    a, b = (baseband(np.asarray(x, float), spacing[0], f, sound_speed=c, axis=0) for x in (frame_a, frame_b))
    verdict = iq_convention(a, b, spacing[0], f, sound_speed=c)
    given = bool(iq.get("conjugate"))
    if verdict[0] == "conjugate":
        fix = (pass_as("leave out --iq-conjugate (read_frames(..., iq_conjugate=False))",
                       "leave out --iq-conjugate") if given else
               pass_as("pass --iq-conjugate (read_frames(..., iq_conjugate=True))", "pass --iq-conjugate"))
        raise OrientationError(
            f"{where}the IQ phase turns against the envelope's motion between the frames ({verdict[2]} windows; the "
            f"other sign convention explains the phases {1 / verdict[1]:.1f} times better): the data look "
            f"demodulated with exp({'-' if given else '+'}2 pi i f t), and registered as they are they would give a "
            f"wrong strain; {fix}, or {override()}", problem="iq-sign")
    if verdict[0] == "frequency":
        from .io.checks import header_frequencies

        fb = verdict[3]
        sign = "" if (fb > 0) != given else " with the other sign convention (--iq-conjugate)"
        found = (f"{where}the IQ phase between the frames turns as for a {abs(fb):.3g} MHz demodulation{sign}, not "
                 f"the {f:g} MHz given ({verdict[2]} windows)")
        freq = ("give the demodulation frequency the scanner recorded (--iq-frequency MHZ; the sampling frequency or "
                "the probe's nominal centre frequency are not it)")
        dx_fix, why = _iq_spacing_fix(iq, spacing, f, fb if (fb > 0) != given else -1.0, metadata, c)
        if dx_fix is None:
            raise OrientationError(f"{found}: with the wrong frequency the strain comes out scaled by about their "
                                   f"ratio; {freq}, or {override()}", problem="iq-frequency")
        dx_iq = float(iq.get("iq_spacing_mm", spacing[0]))
        fix = _pass_spacing(f"{dx_fix:.5g}, {float(spacing[1]):g}", why)
        k = dx_fix / dx_iq
        off = f"{k:.3g} times too small" if k > 1 else f"{1 / k:.3g} times too large"
        spacing_words = (f"the axial spacing {dx_iq:g} mm looks {off} (a spacing off by a factor turns the phases "
                         f"as a frequency off by its inverse): pass {fix}")
        demod = header_frequencies(metadata).get("demod_mhz")
        if demod is not None and abs(demod[0] / f - 1.0) <= 0.01:      # the frequency is the file's own
            raise OrientationError(f"{found}, which is the demodulation frequency the file states ({demod[1]}): "
                                   f"{spacing_words}; or {override()}", problem="iq-spacing")
        raise OrientationError(f"{found}: with the wrong frequency the strain comes out scaled by about their ratio; "
                               f"{freq}; or, if {f:g} MHz is right, {spacing_words}; or {override()}",
                               problem="iq-frequency")
    return verdict
