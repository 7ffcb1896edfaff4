"""Where the echo is: the rectangle of an RF frame pair that holds usable echo, and registration inside it.

A recording as made has regions without usable echo: depth where the attenuated echo has sunk to the receiver's
noise floor, lines outside the aperture or zero-padded rows, samples clipped by the converter.  Fully developed
speckle and noise alone have the same envelope statistics (Rayleigh, envelope SNR 1.91; J. W. Goodman, *Speckle
Phenomena in Optics*, 2007, ch. 3), so the statistics cannot tell them apart; the *level* can.
:func:`find_echo` works on the envelope power (``|analytic signal|^2`` along the beam, :func:`femreg.speckle.envelope`):

* rows and lines whose RF is zero throughout hold no signal (the envelope leaks into them, the RF does not);
* a depth profile, the median over (about :data:`PROFILE_LINES`) lines of each row's envelope power in dB (the
  median: an anechoic region in some lines does not pull the row down), smoothed over :data:`SMOOTH_PERIODS` RF
  periods;
* the noise floor: its quietest rows (the :data:`FLOOR_PERCENTILE`-th percentile of the profile), the echo level
  its :data:`ECHO_PERCENTILE`-th percentile; a profile spanning less than :data:`MIN_RANGE_DB` has no floor to
  tell apart and nothing is excluded for its level;
* the echo SNR of a row, ``10 log10(P / P_floor - 1)`` (echo power over noise power), with hysteresis: the echo
  region spans every run of at least a smoothing length of rows reaching :data:`SEED_SNR_DB` and extends from
  there while the SNR stays at or above :data:`MIN_SNR_DB` (0 dB: the echo as strong as the noise, the level
  3 dB above the floor).  Noise that a time-gain compensation lifts with depth above the floor counts as echo
  (the level cannot tell it; :func:`unmatched_crop` finds it where the block matching of the registration's
  start does not match, for :func:`femreg.register`, :func:`femreg.track` and :func:`femreg.elastogram`);
* the same along the lines, on the rows kept (the median RF power of each line, which for Gaussian RF is the
  envelope's times :data:`RF_TO_ENVELOPE_POWER`), against the depth profile's floor;
* a veto from the pair: electronic noise is independent from frame to frame while echo moves with the tissue,
  so a strip whose envelope still matches the other frame anywhere (best NCC over small shifts at least
  :data:`ECHO_NCC`) holds echo and is kept (a weak deep echo without noise floor, e.g. uncompensated attenuation,
  or echo beyond an anechoic band); a deep strip as far as it matches (its pieces scanned from the bottom up,
  :func:`_followed_rows`): the noise below a weak echo that still matches is left out with the rest;
* saturation: a frame with more than :data:`CLIP_FRACTION` of its samples at its extreme magnitude is clipped;
  rows and lines at the region's edges with more than :data:`CLIP_ROW_FRACTION` clipped samples are excluded.

Only edge strips can be left out (the mesh is a rectangle); saturated rows inside are reported.  Measured on
simulated pairs with attenuation and no time-gain compensation (forward.pairs, 3 / 7.5 / 12 MHz, floor at 40-80 %
of the depth): the detected depth within -0.8 .. +1.0 mm of where the echo power equals the noise power.
:func:`crop_for` turns the detection, or a user's ``roi`` / ``depth`` in mm, into the crop of the frames that
:func:`femreg.register` and :func:`femreg.track` register; their results keep the full frames' pixel grid and say
what was left out.
"""
from __future__ import annotations

import contextlib
import contextvars
import time
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d

from .errors import InputError, pass_as
from .image import validate_image, validate_spacing
from .mesh import DEFAULT_MARGIN
from .speckle import envelope, rf_period

__all__ = ["EchoRegion", "Cut", "DataMask", "unmatched_crop", "MATCHED_NCC", "UNMATCHED_FRACTION", "noise_share", "registering_crop", "crop_noise_share", "as_data_mask", "find_echo", "find_fill", "find_rf_fan", "fill_level", "crop_for", "crop_request", "Crop", "region_from_mm", "rf_like", "MIN_SNR_DB", "SEED_SNR_DB",
           "MIN_RANGE_DB", "ECHO_NCC", "CLIP_FRACTION", "CLIP_ROW_FRACTION"]

#: A value covering more than this fraction of an envelope / B-mode frame (and the same pixels of the other frame)
#: is fill, not image (:func:`find_fill`).
FILL_FRACTION = 0.02
#: Echo SNR (dB, echo power over noise power) below which a row or line holds no usable echo.
MIN_SNR_DB = 0.0
#: Echo SNR (dB) a row or line must reach to start the echo region (hysteresis above :data:`MIN_SNR_DB`).
SEED_SNR_DB = 6.0
#: A level profile spanning less than this (dB, echo percentile minus floor percentile) has no noise floor.
MIN_RANGE_DB = 10.0
#: Percentiles of the smoothed profile taken as the noise floor and as the echo level.
FLOOR_PERCENTILE = 1.0
ECHO_PERCENTILE = 90.0
#: Smoothing of the depth profile, in RF periods (about five wavelengths, a few speckle lengths).
SMOOTH_PERIODS = 10.0
#: Lines (about) the depth profile is measured on.
PROFILE_LINES = 64
#: Rows (at most) the line profile is measured on.
PROFILE_ROWS = 1024
#: Median envelope power over median RF power of Gaussian RF: 2 ln 2 / 0.4549 (median of chi-square, 1 dof).
RF_TO_ENVELOPE_POWER = 2.0 * np.log(2.0) / 0.454936
#: Smoothing of the line profile, in lines.
SMOOTH_LINES = 3
#: Best envelope NCC between the frames (over small shifts) at or above which a candidate strip holds echo.
ECHO_NCC = 0.5
#: Height of the pieces of a strip matched one by one, in RF periods: short enough that the strain within one
#: (up to 5 %) shifts its speckle by much less than a pulse length.
VETO_PERIODS = 10.0
#: Fewest samples of such a piece (taller pieces on narrow strips): unrelated frames then match with NCC at most
#: 0.09 (white noise) and 0.31 (speckle, i.e. noise filtered like the echo) at the best of all shifts and pieces
#: (measured, 3 / 7.5 / 12 MHz probes, strips of 4 lines to the full width).
VETO_SAMPLES = 4096
#: RF magnitude, relative to the frame's largest, at or below which a whole row or line holds no signal.
DEAD_LEVEL = 1e-12
#: Fraction of a frame's samples at its extreme magnitude above which it counts as clipped.
CLIP_FRACTION = 1e-3
#: Fraction of clipped samples above which a row or line is saturated.
CLIP_ROW_FRACTION = 0.02


def _mm_span(lo, hi) -> str:
    """'a-b mm' of two cell edges (mm), each to 0.1 mm."""
    # + 0.0: the first cell's edge half a sample above a zero origin reads 0.0, not -0.0
    a, b = (round(v, 1) + 0.0 for v in (lo, hi))
    return f"{a:.1f}-{b:.1f} mm"


@dataclass(frozen=True)
class Cut:
    """One strip of the frames an :class:`EchoRegion` leaves out (or names), as data; :attr:`text` is its part of
    the region's ``excluded``.

    axis : "depth" (rows) or "lines" (columns).  side : "above" / "below" (rows cut at the top / bottom), "left" /
    "right" (lines), None (a strip named by its span: saturated rows or lines), "kept" (saturated rows inside the
    region, kept).  lo, hi : the strip's outer pixel-cell edges, mm along ``axis``.  why : the reason, as said after
    the place ("excluded: no signal (zero samples)", "excluded: the frames do not match there (...)", ...)."""

    axis: str
    side: str | None
    lo: float
    hi: float
    why: str

    @property
    def edge(self) -> float:
        """mm: where the region begins (``side`` "above") or ends ("below")."""
        return self.hi if self.side == "above" else self.lo

    @property
    def span(self) -> str:
        """'a-b mm' of :attr:`lo`, :attr:`hi`, each to 0.1 mm."""
        return _mm_span(self.lo, self.hi)

    @property
    def text(self) -> str:
        if self.side in ("above", "below"):
            return f"{self.axis} {self.side} {self.edge:.1f} mm {self.why}"
        if self.side == "kept":
            return f"saturated rows at {self.span} {self.why}"
        if self.side is None:
            return f"{self.axis} {self.span} {self.why}"
        return f"lines at {self.span} ({self.side}) {self.why}"


def _said(cuts) -> str | None:
    """An :class:`EchoRegion`'s ``excluded`` from its :class:`Cut` s (None: nothing cut)."""
    return "; ".join(c.text for c in cuts) or None


@dataclass
class EchoRegion:
    """The rectangle of usable echo of a frame pair (:func:`find_echo`).

    rows, cols : (start, stop) pixel index ranges (half-open) of the rectangle; ``shape``, ``spacing``,
    ``origin`` the frames' grid (mm).  ``excluded``: what was left out and why (None: nothing).
    ``floor_db`` / ``echo_db``: noise floor and echo level of the depth profile, dB of the envelope in the data's
    units (NaN where not measured).
    """

    rows: tuple
    cols: tuple
    shape: tuple
    spacing: tuple
    origin: tuple
    excluded: str | None = None
    floor_db: float = float("nan")
    echo_db: float = float("nan")
    #: (n_axial, n_lateral) bool, True at the fill pixels (:func:`find_fill`), or None; ``fill_value`` its level
    fill: np.ndarray | None = None
    fill_value: float = float("nan")
    #: ((r0, r1), (c0, c1)) the largest rectangle without fill of a :func:`fan_region`, or None
    rectangle: tuple | None = None
    #: whether rows were left out at ``floor_db`` that did not match the other frame: the noise itself was seen
    #: (not only the quietest echo)
    noise_seen: bool = False
    #: what was cut, strip by strip (:class:`Cut`; ``excluded`` is their text), for a detected region; () for a
    #: given box or a fan's fill, whose ``excluded`` is its own
    cuts: tuple = ()
    #: "roi" / "depth" for a user's box (:func:`region_from_mm`: ``roi_mm`` is the box kept), else None
    given: str | None = None

    @property
    def row_cuts(self) -> tuple:
        """The :class:`Cut` s of rows left out (at the top, the bottom, or saturated; not the saturated rows kept)."""
        return tuple(c for c in self.cuts if c.axis == "depth" and c.side != "kept")

    @property
    def full(self) -> bool:
        return tuple(self.rows) == (0, self.shape[0]) and tuple(self.cols) == (0, self.shape[1])


    @property
    def roi_mm(self) -> tuple:
        """(x0, x1, y0, y1) mm: the rectangle's outer pixel-cell edges."""
        dx, dy = self.spacing
        ox, oy = self.origin
        return (ox + (self.rows[0] - 0.5) * dx, ox + (self.rows[1] - 0.5) * dx,
                oy + (self.cols[0] - 0.5) * dy, oy + (self.cols[1] - 0.5) * dy)


def _db(p):
    p = np.asarray(p, float)
    tiny = 1e-30 * max(float(np.max(p)), 1e-300)
    return 10.0 * np.log10(p + tiny)


def _live_span(live):
    """(first, last + 1) of the True entries of ``live`` ((0, 0) when none)."""
    k = np.flatnonzero(live)
    return (int(k[0]), int(k[-1]) + 1) if k.size else (0, 0)


def _profile(power, live, w):
    """Smoothed level profile (dB) of the medians ``power``, its floor and echo percentiles over the ``live``
    entries; the dead ones take the floor before smoothing (no dip below it)."""
    db = _db(np.where(live, power, 0.0))
    if not live.any():
        return db, 0.0, 0.0
    fill = float(np.percentile(db[live], FLOOR_PERCENTILE))
    sm = uniform_filter1d(np.where(live, db, fill), w, mode="nearest")
    return sm, float(np.percentile(sm[live], FLOOR_PERCENTILE)), float(np.percentile(sm[live], ECHO_PERCENTILE))


def _echo_run(level_db, floor_db, min_len, live):
    """(a, b) half-open run of rows with echo (hysteresis rule of the module docstring: from the first to the last
    run of at least ``min_len`` rows reaching :data:`SEED_SNR_DB`, so that a few rows of edge effects do not
    count, extended while the SNR stays at :data:`MIN_SNR_DB`; ``live``: False where the data hold no signal at
    all), and the SNR profile."""
    snr = _db(np.maximum(10.0 ** ((level_db - floor_db) / 10.0) - 1.0, 1e-6))
    snr[~live] = -np.inf
    seed = np.concatenate([[False], snr >= SEED_SNR_DB, [False]])
    edges = np.flatnonzero(np.diff(seed.astype(np.int8)))
    runs = [(int(s), int(e)) for s, e in zip(edges[0::2], edges[1::2]) if e - s >= min_len]
    if not runs:
        return (0, 0), snr
    a, b = runs[0][0], runs[-1][1]          # never less than every bright run: no echo is cut off
    while a > 0 and snr[a - 1] >= MIN_SNR_DB:
        a -= 1
    while b < snr.size and snr[b] >= MIN_SNR_DB:
        b += 1
    return (a, b), snr


def _chunk_cuts(rows, n, cols, row_step, chunk):
    """Row boundaries of the pieces :func:`_strip_ncc` measures ``rows`` in: equal heights, none shorter than
    ``chunk`` rows taken every ``row_step``-th row (and enough samples for a noise NCC near 0)."""
    q = int(row_step)
    chunk = max(int(chunk), -(-VETO_SAMPLES // max(1, cols[1] - cols[0])))
    top, bottom = rows[0], min(rows[1], n)
    k = max(1, (bottom - top) // (chunk * q))
    return np.linspace(top, bottom, k + 1).round().astype(int)


def _chunk_ncc(ea, eb, r0, r1, cols, max_shift, q, max_lat) -> float:
    """Best NCC of the envelope ``ea[r0:r1, cols]`` (every ``q``-th row) against ``eb`` shifted by up to
    ``max_shift`` rows and ``max_lat`` lines; stops at :data:`ECHO_NCC`."""
    best = -1.0
    n, m = eb.shape
    c0, c1 = max(0, cols[0]), min(m, cols[1])
    for s in range(-max_shift, max_shift + 1, q):
        lo, hi = max(r0, -s), min(r1, n - s)
        if hi - lo < 2 * q:
            continue
        for t in range(-max_lat, max_lat + 1):
            cl, ch = max(c0, -t), min(c1, m - t)
            if ch - cl < 1:
                continue
            a = ea[lo:hi:q, cl:ch].ravel()
            b = eb[lo + s:hi + s:q, cl + t:ch + t].ravel()
            a = a - a.mean()
            b = b - b.mean()
            d = float(np.sqrt(np.dot(a, a) * np.dot(b, b)))
            if d > 0:
                best = max(best, float(np.dot(a, b)) / d)
                if best >= ECHO_NCC:
                    return best
    return best


def _strip_ncc(ea, eb, rows, cols, max_shift, row_step, max_lat=1, chunk=256) -> float:
    """Best NCC of the envelope ``ea[rows, cols]`` against ``eb`` shifted by up to ``max_shift`` rows (steps of
    ``row_step``) and ``max_lat`` lines, in chunks of at most ``chunk`` rows taken every ``row_step``-th row (the
    envelope is smooth over it): the best over the chunks, so that echo anywhere in the strip counts; stops at
    :data:`ECHO_NCC`."""
    best = -1.0
    cuts = _chunk_cuts(rows, eb.shape[0], cols, row_step, chunk)
    for r0, r1 in zip(cuts[:-1], cuts[1:]):
        best = max(best, _chunk_ncc(ea, eb, r0, r1, cols, max_shift, int(row_step), max_lat))
        if best >= ECHO_NCC:
            return best
    return best


def _followed_rows(ea, eb, rows, cols, max_shift, row_step, *, max_lat=1, chunk=256):
    """The row a deep strip's echo reaches: scanning the strip's chunks (:func:`_strip_ncc`) from its bottom up,
    the lower edge of the first chunk whose envelope still matches the other frame; None when none does.  Noise
    below the echo is independent from frame to frame, so the chunks that hold only noise are left out with the
    rest of the strip."""
    cuts = _chunk_cuts(rows, eb.shape[0], cols, row_step, chunk)
    for r0, r1 in reversed(list(zip(cuts[:-1], cuts[1:]))):
        if _chunk_ncc(ea, eb, r0, r1, cols, max_shift, int(row_step), max_lat) >= ECHO_NCC:
            return int(r1)
    return None


def _clipped(mags):
    """Boolean map of clipped samples (any frame; ``mags``: the frames' |RF|), or None when none is clipped."""
    out = None
    for f in mags:
        c = float(np.max(f))
        if not c > 0:
            continue
        m = f >= c * (1.0 - 1e-9)
        if np.mean(m) > CLIP_FRACTION:
            out = m if out is None else (out | m)
    return out


def _span(lo, hi, origin, step):
    """'a-b mm' of pixel indices [lo, hi) (cell edges)."""
    return _mm_span(*_edges(lo, hi, origin, step))


def _edges(lo, hi, origin, step):
    """The outer cell edges (mm) of pixel indices [lo, hi)."""
    return origin + (lo - 0.5) * step, origin + (hi - 0.5) * step


def fill_level(frame) -> float | None:
    """The candidate fill level of an envelope / B-mode ``frame``: its lowest value (fill is black; a saturated
    bright layer is tissue) when that covers more than :data:`FILL_FRACTION` of it, else None."""
    v = float(np.min(frame))
    return v if np.count_nonzero(frame == v) > FILL_FRACTION * np.size(frame) else None


def _fill_reason(value, fraction) -> str:
    """The start of what a fill's exclusion says (:func:`find_fill`, :func:`fan_region`)."""
    return (f"fill of value {value:g} ({100 * fraction:.0f} % of the frame: the wedges of a scan-converted sector or "
            f"a blanked margin, fixed while the tissue moves) excluded: ")


def find_rf_fan(ref, mov, spacing, origin) -> EchoRegion | None:
    """The fan of an RF pair scan-converted onto a Cartesian grid (validated (n_axial, n_lateral) frames,
    ``spacing``, ``origin`` mm): zero samples in both frames, in pieces touching the frame's edge, together more
    than :data:`FILL_FRACTION` of it and not only whole rows or lines (those are dead rows / lines,
    :func:`find_echo`), as :func:`find_fill` for a B-mode; None otherwise.  Registered over the rectangle, the
    fixed zero wedges pull the field (a 3.5 MHz convex pair, 1617 x 666 samples, 39 % wedges: FAILED, peak
    hopping at the wedges' edges)."""
    from scipy import ndimage

    zero = (ref == 0) & (mov == 0)
    if zero.sum() <= FILL_FRACTION * ref.size:
        return None
    labels, _ = ndimage.label(zero)
    edge = np.unique(np.r_[labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    fill = np.isin(labels, edge[edge > 0])
    rows, cols = np.flatnonzero((~fill).any(axis=1)), np.flatnonzero((~fill).any(axis=0))
    if rows.size < 2 or cols.size < 2:
        return None
    box = fill[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    if box.sum() <= FILL_FRACTION * ref.size:
        return None                     # zero rows or lines at the edges only: find_echo's dead ones
    dx, dy = (float(t) for t in spacing)
    ox, oy = (float(t) for t in origin)
    (a, b), (c, d) = _fill_rectangle(fill, f"{100 * fill.mean():.0f} % of the reference is zero samples")
    return EchoRegion((a, b), (c, d), fill.shape, (dx, dy), (ox, oy), _fill_reason(0.0, fill.mean()), fill=fill,
                      fill_value=0.0)


def find_fill(ref, mov, spacing, origin) -> EchoRegion | None:
    """The largest rectangle of an envelope / B-mode pair (validated (n_axial, n_lateral) frames, ``spacing``,
    ``origin`` mm) without fill, or None without fill.

    Fill is the reference's lowest value where the moving frame has it too, in pieces that touch the frame's
    edge, together more than :data:`FILL_FRACTION` of it: the black wedges around a scan-converted convex
    or sector image, a blanked margin.  It is fixed on the screen while the tissue moves: registered, its edges pull the
    displacement to zero (a fan-masked L12 B-mode pair: 6.1 -> 78 % strain error, FAILED).  The mesh is a
    rectangle (module docstring), so the largest axis-parallel rectangle free of fill in either frame is kept
    (:func:`_largest_rectangle`)."""
    from scipy import ndimage

    v = fill_level(ref)
    if v is None:
        return None
    # fill in both frames, in pieces that touch the frame's edge: speckle clipped to black inside the tissue
    # (a B-mode's darkest level) moves with it and lies inside
    labels, _ = ndimage.label((ref == v) & (mov == v))
    edge = np.unique(np.r_[labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    fill = np.isin(labels, edge[edge > 0])
    if fill.sum() <= FILL_FRACTION * ref.size:
        return None
    dx, dy = (float(t) for t in spacing)
    ox, oy = (float(t) for t in origin)
    (a, b), (c, d) = _fill_rectangle(fill, f"{100 * fill.mean():.0f} % of the reference is the fill value {v:g}")
    why = (_fill_reason(v, fill.mean()) + f"registered on the largest rectangle without it, depth "
           f"{ox + (a - 0.5) * dx:.1f}-{ox + (b - 0.5) * dx:.1f} mm, lines at "
           f"{oy + (c - 0.5) * dy:.1f}-{oy + (d - 0.5) * dy:.1f} mm (roi= / --roi to choose another)")
    return EchoRegion((a, b), (c, d), fill.shape, (dx, dy), (ox, oy), why, fill=fill, fill_value=v)


def _fill_rectangle(fill, what):
    """((r0, r1), (c0, c1)): the largest rectangle without ``fill`` (:func:`_largest_rectangle`);
    :class:`InputError` saying ``what`` when it holds fewer than 2 x 2 pixels."""
    (a, b), (c, d) = _largest_rectangle(~fill)
    if b - a < 2 or d - c < 2:
        raise InputError(f"the frames hold no rectangle of image: {what}; give "
                         + pass_as("roi=(x0, x1, y0, y1) mm (CLI: --roi)", "--roi X0 X1 Y0 Y1 (mm)"))
    return (a, b), (c, d)


#: Fraction of the frames' depth (extent along the beam, mm) that the tissue may move, per axis: the fill mask is
#: dilated by it (plus the spline support, :data:`SPLINE_SUPPORT` pixels) before the image term leaves it out.
FAN_MOTION = 0.03
#: Pixels of the cubic B-spline's support: a pixel closer than this to fill reads fill when interpolated.
SPLINE_SUPPORT = 2.0


def fan_weights(fill, spacing) -> np.ndarray:
    """(n_axial, n_lateral) bool, True where eq:IR compares the frames inside a fan of ``fill`` (bool, True at
    fill; ``spacing`` mm): farther than ``SPLINE_SUPPORT + max(SPLINE_SUPPORT, FAN_MOTION depth / spacing)``
    pixels per axis (an ellipse) from any fill pixel.  Nearer, the reference spline reads the fill's step, and the
    moving frame moved by up to :data:`FAN_MOTION` of the depth reads the fixed wedge instead of tissue."""
    from scipy.ndimage import distance_transform_edt

    fill = np.asarray(fill, bool)
    sp = np.asarray(spacing, float)
    depth = float(fill.shape[0] * sp[0])
    r = SPLINE_SUPPORT + np.maximum(SPLINE_SUPPORT, FAN_MOTION * depth / sp)        # pixels per axis
    if not fill.any():
        return np.ones(fill.shape, bool)
    return distance_transform_edt(~fill, sampling=1.0 / r) > 1.0


def fan_region(region: EchoRegion) -> EchoRegion:
    """The bounding box of the pixels without fill of a :func:`find_fill` (or :func:`given_fan`) region (the fan
    registered whole: fill and its neighbourhood weighted 0 in eq:IR, :func:`fan_weights`)."""
    fan = ~region.fill
    rows, cols = np.flatnonzero(fan.any(axis=1)), np.flatnonzero(fan.any(axis=0))
    (dx, dy), (ox, oy) = region.spacing, region.origin
    start = region.excluded if np.isnan(region.fill_value) else _fill_reason(region.fill_value, region.fill.mean())
    why = (start + f"the image term left out there and within "
           f"{SPLINE_SUPPORT:g} pixels + {100 * FAN_MOTION:g} % of the depth of it, the field carried by the "
           f"regulariser, results NaN outside the fan (roi= / --roi to choose a rectangle)")
    return EchoRegion((int(rows[0]), int(rows[-1]) + 1), (int(cols[0]), int(cols[-1]) + 1), region.shape,
                      region.spacing, region.origin, why, fill=region.fill, fill_value=region.fill_value,
                      rectangle=(tuple(region.rows), tuple(region.cols)))


def given_fan(mask, spacing, origin) -> EchoRegion | None:
    """The :func:`fan_region` of a user's ``data_mask`` ((n_axial, n_lateral) bool, True where the frames hold
    data, validated by :func:`as_data_mask`), or None when it is True everywhere."""
    fill = ~np.asarray(mask, bool)
    if not fill.any():
        return None
    dx, dy = (float(t) for t in spacing)
    ox, oy = (float(t) for t in origin)
    rect = _fill_rectangle(fill, f"{100 * fill.mean():.0f} % of the frame lies outside the given data_mask")
    why = f"outside the given data_mask ({100 * fill.mean():.0f} % of the frame) excluded: "
    return fan_region(EchoRegion(rect[0], rect[1], fill.shape, (dx, dy), (ox, oy), why, fill=fill))


@dataclass(frozen=True)
class DataMask:
    """Where eq:IR compares a pair of frames of one shape: the form in which :func:`femreg.register` hands a fan
    (:func:`fan_region`, or a user's ``data_mask``) to its registration on the cropped frames.

    inside : (n_axial, n_lateral) bool
        True where the frames hold data (the fan); the frames are normalised over it
        (:func:`femreg.image.normalize_pair`).
    weights : (n_axial, n_lateral) bool
        True where eq:IR compares the frames (:func:`fan_weights`: the fill and its neighbourhood weighted 0).
    rectangle : (row slice, column slice) or None
        The largest rectangle without fill, where the speckle statistics and the pyramid start are taken; None:
        the whole frames.
    """

    inside: np.ndarray
    weights: np.ndarray
    rectangle: tuple | None = None


def as_data_mask(mask, shape, spacing) -> DataMask | None:
    """``mask`` as :func:`femreg.register` uses it on frames of ``shape`` (``spacing`` mm): None stays None; a
    :class:`DataMask` is kept; a bool (n_axial, n_lateral) array, True where there are data, gives its
    :func:`fan_weights` and largest rectangle (None when it is True everywhere).  :class:`InputError` for another
    type, dtype or shape, or a mask without a 2 x 2 rectangle."""
    if mask is None:
        return None
    shape = tuple(int(s) for s in shape)
    if isinstance(mask, DataMask):
        got = (np.shape(mask.inside), np.shape(mask.weights))
        if got != (shape, shape):
            raise InputError(f"data_mask is for frames of shape {got[0]}, the frames are {shape}")
        return mask
    arr = np.asarray(mask)
    if arr.dtype != bool or arr.shape != shape:
        raise InputError(f"data_mask must be a bool array of the frames' shape {shape} (True where there are "
                         f"data), got {arr.dtype} {arr.shape}")
    fill = ~arr
    if not fill.any():
        return None
    (a, b), (c, d) = _fill_rectangle(fill, f"{100 * fill.mean():.0f} % of the frame lies outside the given "
                                           f"data_mask")
    return DataMask(arr.copy(), fan_weights(fill, spacing), (slice(a, b), slice(c, d)))


def _largest_rectangle(mask):
    """((r0, r1), (c0, c1)) half-open index ranges of the largest-area all-True axis-parallel rectangle of a 2D
    bool ``mask``: the maximal rectangle of a histogram per row, with a stack (linear per row)."""
    n, m = mask.shape
    heights = np.zeros(m, int)
    best, box = 0, ((0, 0), (0, 0))
    for i in range(n):
        heights = np.where(mask[i], heights + 1, 0)
        stack = []                                   # column indices of increasing heights
        for j in range(m + 1):
            h = int(heights[j]) if j < m else 0
            start = j
            while stack and stack[-1][1] >= h:
                s0, hs = stack.pop()
                if hs * (j - s0) > best:
                    best, box = hs * (j - s0), ((i - hs + 1, i + 1), (s0, j))
                start = s0
            stack.append((start, h))
    return box


def rf_like(image) -> bool:
    """True for an RF frame: zero mean on every line within a fraction of its RMS (envelope, B-mode and other
    one-signed intensity images are not; their level says nothing about echo against noise)."""
    img = np.asarray(image, float)
    if img.ndim != 2 or img.shape[0] < 64 or img.shape[1] < 4:
        return False
    rms = float(np.sqrt(np.mean(img ** 2)))
    return rms > 0 and float(np.sqrt(np.mean(np.mean(img, axis=0) ** 2))) < 0.1 * rms


def find_echo(reference, moving=None, *, spacing, origin=(0.0, 0.0)) -> EchoRegion:
    """Detect the rectangle of usable echo of an RF frame (pair) (module docstring).

    Parameters
    ----------
    reference, moving : (n_axial, n_lateral) RF frames; ``moving`` (optional) adds the frame-to-frame veto and
        its own clipping.
    spacing, origin : (2,) mm

    Returns
    -------
    EchoRegion (``excluded`` None when the whole frame holds echo).
    """
    ref = validate_image(reference, "reference image")
    mov = None if moving is None else validate_image(moving, "moving image")
    spacing, origin = validate_spacing(spacing, origin)
    return _find_echo(ref, mov, spacing, origin)


def _find_echo(ref, mov, spacing, origin) -> EchoRegion:
    """:func:`find_echo` on validated frames."""
    n, m = ref.shape
    dx, dy = float(spacing[0]), float(spacing[1])
    ox, oy = float(origin[0]), float(origin[1])
    full = EchoRegion((0, n), (0, m), (n, m), (dx, dy), (ox, oy))
    if not rf_like(ref):
        return full
    envs = []                        # the frames' envelopes, for the veto only
    # lines and rows without any signal (zero samples) are dead; the envelope leaks into them, the RF does not
    mag = np.abs(ref)
    top = float(np.max(mag))
    live_c = np.max(mag, axis=0) > DEAD_LEVEL * top
    live_r = np.max(mag[:, live_c], axis=1) > DEAD_LEVEL * top
    lines = np.flatnonzero(live_c)
    lines = lines[::max(1, lines.size // PROFILE_LINES)]     # the depth profile from about 64 lines: as good
    row_med = np.median(envelope(ref[:, lines]) ** 2, axis=1)
    period = rf_period(ref[:, ::max(1, m // 32)], spacing)
    w = int(max(3, round(SMOOTH_PERIODS * period / dx)))
    row_db, floor, echo = _profile(row_med, live_r, w)
    reasons = []

    def veto_args(rows):
        if not envs:
            envs.extend([envelope(ref), envelope(mov)])
        depth = ox + rows[1] * dx
        max_shift = int(np.ceil(max(3.0 * period, 0.05 * abs(depth)) / dx))
        step = max(1, int(round(period / (2.0 * dx))))     # the envelope varies over a pulse length
        chunk = max(8, int(round(VETO_PERIODS * period / (step * dx))))
        return max_shift, step, chunk

    def veto(rows, cols):
        """True when the strip still matches the other frame (echo moving with the tissue)."""
        if mov is None or rows[1] - rows[0] < 2 or cols[1] - cols[0] < 1:
            return False
        max_shift, step, chunk = veto_args(rows)
        return _strip_ncc(envs[0], envs[1], rows, cols, max_shift, step, chunk=chunk) >= ECHO_NCC

    def followed(rows):
        """The row the echo of a deep strip reaches (:func:`_followed_rows`), or None."""
        if mov is None or rows[1] - rows[0] < 2:
            return None
        max_shift, step, chunk = veto_args(rows)
        return _followed_rows(envs[0], envs[1], rows, (0, m), max_shift, step, chunk=chunk)

    has_floor = echo - floor >= MIN_RANGE_DB
    (a, b) = _echo_run(row_db, floor, max(w, n // 20), live_r)[0] if has_floor else _live_span(live_r)
    if b <= a:
        a, b = _live_span(live_r)
    at = f" at {_echo_span(row_db, echo, ox, dx)}"
    if a > 0 and has_floor and veto((0, a), (0, m)):
        a = _live_span(live_r)[0]
    if a > 0:
        reasons.append(Cut("depth", "above", *_edges(0, a, ox, dx), _why(has_floor and live_r[:a].any(), echo, floor,
                                                                        at)))
    # a deep strip that still follows the tissue is kept as far as it does (to the live span's end at most): the
    # noise below a weak deep echo is cut off, not kept with it
    if b < n and has_floor:
        k = followed((b, n))
        if k is not None:
            b = min(k, _live_span(live_r)[1])
    if b < n:
        reasons.append(Cut("depth", "below", *_edges(b, n, ox, dx), _why(has_floor and live_r[b:].any(), echo, floor,
                                                                        at)))
    # rows left out for their level that the veto did not keep: noise, its floor seen
    seen = has_floor and (bool(live_r[b:].any()) or bool(live_r[:a].any()))
    # the lines, over the rows kept
    # the line profile from the RF power: no envelope of every line needed; for Gaussian RF (speckle and noise
    # alike) the median of RF^2 is the envelope's median power times a constant
    q = max(1, (b - a) // PROFILE_ROWS)
    col_med = np.median(ref[a:b:q] ** 2, axis=0) * RF_TO_ENVELOPE_POWER
    live_c &= np.max(mag[a:b], axis=0) > DEAD_LEVEL * top
    col_db, cfloor, cecho = _profile(col_med, live_c, SMOOTH_LINES)
    if has_floor:
        cfloor = floor
    c_floor = cecho - cfloor >= MIN_RANGE_DB
    (c0, c1) = _echo_run(col_db, cfloor, max(SMOOTH_LINES, m // 20), live_c)[0] if c_floor else _live_span(live_c)
    if c1 <= c0:
        c0, c1 = _live_span(live_c)
    for lo, hi, side in ((0, c0, "left"), (c1, m, "right")):
        if hi <= lo:
            continue
        if c_floor and veto((a, b), (lo, hi)):
            c0, c1 = (_live_span(live_c)[0], c1) if side == "left" else (c0, _live_span(live_c)[1])
            lo, hi = (0, c0) if side == "left" else (c1, m)
            if hi <= lo:
                continue
            reasons.append(Cut("lines", side, *_edges(lo, hi, oy, dy), _why(False, 0, 0)))
        else:
            reasons.append(Cut("lines", side, *_edges(lo, hi, oy, dy), _why(c_floor and live_c[lo:hi].any(), cecho,
                                                                             cfloor)))
    # saturation at the edges of the rectangle
    clip = _clipped([mag] if mov is None else [mag, np.abs(mov)])
    if clip is not None:
        rows_sat = np.mean(clip[:, c0:c1], axis=1) > CLIP_ROW_FRACTION
        a0, b0 = a, b
        while a < b and rows_sat[a]:
            a += 1
        while b > a and rows_sat[b - 1]:
            b -= 1
        cols_sat = np.mean(clip[a:b], axis=0) > CLIP_ROW_FRACTION
        k0, k1 = c0, c1
        while c0 < c1 and cols_sat[c0]:
            c0 += 1
        while c1 > c0 and cols_sat[c1 - 1]:
            c1 -= 1
        frac = float(np.mean(clip))
        for lo, hi, what, o, st in ((a0, a, "depth", ox, dx), (b, b0, "depth", ox, dx), (k0, c0, "lines", oy, dy),
                                    (c1, k1, "lines", oy, dy)):
            if hi > lo:
                reasons.append(Cut(what, None, *_edges(lo, hi, o, st), f"excluded: saturated (more than "
                                   f"{CLIP_ROW_FRACTION:.0%} of the samples clipped; {frac:.1%} of the frame)"))
        inner = np.flatnonzero(np.mean(clip[a:b, c0:c1], axis=1) > CLIP_ROW_FRACTION)
        if inner.size:
            reasons.append(Cut("depth", "kept", *_edges(a + int(inner[0]), a + int(inner[-1]) + 1, ox, dx),
                               "kept (inside the echo region)"))
    return EchoRegion((a, b), (c0, c1), (n, m), (dx, dy), (ox, oy), _said(reasons), floor, echo, noise_seen=seen,
                      cuts=tuple(reasons))


def _why(has_floor, lvl, flr, echo_at=""):
    """Why a strip of frames or volumes is left out: no signal, or echo too close to the noise floor."""
    if not has_floor:
        return "excluded: no signal (zero samples)"
    return (f"excluded: level within {MIN_SNR_DB + 3.0:.0f} dB of the noise floor {flr:.1f} dB "
            f"(echo {lvl:.1f} dB{echo_at})")


def _echo_span(row_db, echo, ox, dx) -> str:
    """Where the depth profile is within 3 dB of the echo level."""
    k = np.flatnonzero(row_db >= echo - 3.0)
    return _span(int(k[0]), int(k[-1]) + 1, ox, dx) if k.size else "-"


#: Median block-matching NCC (90th percentile over the rows of windows) the frames must reach for
#: :func:`unmatched_crop` to look for noise at depth: below it the whole pair matches poorly (a rotation, large
#: strain) and a low row says nothing.
MATCHED_NCC = 0.7
#: Rows of windows at the bottom whose median NCC is below this fraction of that level hold noise
#: (:func:`unmatched_crop`; NCC S / (S + N): half at an echo as strong as the noise).
UNMATCHED_FRACTION = 0.5


def unmatched_crop(blockmatch, shape, spacing, origin=(0.0, 0.0), margin=None) -> Crop | None:
    """The frames cut above the rows of block-matching windows at their bottom that do not match, or None.

    Noise that a time-gain compensation lifts with depth keeps the level of the echo, so :func:`find_echo` cannot
    tell it (module docstring); it does not move with the tissue, so windows there find no match even after
    block matching has searched out the motion.  ``blockmatch``: the registration's
    :class:`femreg.blockmatch.BlockMatchResult` on these frames ((n_axial, n_lateral) ``shape``, ``spacing``,
    ``origin`` mm).  Where the rows' median NCC reaches :data:`MATCHED_NCC` (90th percentile) and at least two
    rows at the bottom, and no more than half of them, fall below :data:`UNMATCHED_FRACTION` of it, the frames
    are cut half-way between the last matching row and the first that does not; None when nothing lies beyond
    the mesh margin."""
    if blockmatch is None or np.ndim(blockmatch.ncc) != 2 or len(blockmatch.x) < 4:
        return None
    med = np.median(np.asarray(blockmatch.ncc, float), axis=1)
    top = float(np.percentile(med, 90))
    if not top >= MATCHED_NCC:
        return None
    k = med.size
    while k > 0 and med[k - 1] < UNMATCHED_FRACTION * top:
        k -= 1
    if med.size - k < 2 or k < med.size / 2:
        return None
    (n, m), (dx, _), (ox, _) = shape, spacing, origin
    x = np.asarray(blockmatch.x, float)
    b = int(np.clip(np.ceil((0.5 * (x[k - 1] + x[k]) - ox) / dx), 1, n))
    mp = _margin_pixels(margin, spacing)
    if b >= n - mp[0]:
        return None
    cut = Cut("depth", "below", *_edges(b, n, ox, dx), (
        f"excluded: the frames do not match there (block-matching NCC {float(med[k:].min()):.2f}-"
        f"{float(med[k:].max()):.2f} against {top:.2f} above: noise, e.g. lifted by a time-gain compensation)"))
    return Crop(EchoRegion((0, b), (0, m), (n, m), tuple(spacing), tuple(origin), cut.text, cuts=(cut,)), mp, False)


def _margin_pixels(margin, spacing, default=DEFAULT_MARGIN) -> np.ndarray:
    """Pixels (voxels) of the mesh margin per axis, as :func:`femreg.mesh.roi_mesh` (:func:`femreg.voxels.roi_mesh_3d`
    with its ``default``) rounds it."""
    m = np.broadcast_to(np.asarray(default if margin is None else margin, float), (len(spacing),))
    if np.any(~np.isfinite(m)) or np.any(m < 0):
        raise InputError(f"margin must be >= 0 mm, got {tuple(m)}")
    return np.ceil(m / np.asarray(spacing, float) - 1e-9).astype(int)


#: Axis names of the messages, frames (2) and volumes (3).
_AXES = ("x (axial)", "y (lateral)", "z (elevational)")


def _extent_text(shape, spacing, origin) -> str:
    lo = np.asarray(origin, float) - 0.5 * np.asarray(spacing, float)
    hi = lo + np.asarray(shape, float) * np.asarray(spacing, float)
    return ", ".join(f"{name} {lo[k]:.4g} to {hi[k]:.4g} mm" for k, name in enumerate(_AXES[:len(shape)]))


def _given(what: str, v) -> str:
    """A given ``roi`` / ``depth`` (mm) in the caller's words: the argument's tuple, or the flag as typed."""
    return pass_as(f"{what} {tuple(float(x) for x in v)} mm", f"--{what} {' '.join(f'{x:g}' for x in v)} (mm)")


def region_from_mm(shape, spacing, origin, *, roi=None, depth=None) -> EchoRegion:
    """The pixel rectangle of a user's ``roi`` (x0, x1, y0, y1) or ``depth`` (d0, d1) mm: the pixels whose centres
    lie inside it.  :class:`InputError` naming the image extent when it leaves the image or holds no pixel."""
    if roi is not None and depth is not None:
        raise InputError("give roi or depth, not both (depth (d0, d1) is roi (d0, d1, y0, y1) over all lines)")
    what = "roi" if roi is not None else "depth"
    val = roi if roi is not None else depth
    try:
        v = np.asarray(val, float).ravel()
    except (TypeError, ValueError):
        v = np.array([np.nan])
    need = 4 if roi is not None else 2
    if v.size != need or not np.all(np.isfinite(v)) or v[0] >= v[1] or (need == 4 and v[2] >= v[3]):
        form, order, flag = (("(x0, x1, y0, y1)", "x0 < x1 and y0 < y1", "--roi X0 X1 Y0 Y1") if need == 4 else
                             ("(d0, d1)", "d0 < d1", "--depth D0 D1"))
        got = " ".join(f"{x:g}" for x in v)
        raise InputError(pass_as(f"{what} must be {form} mm with {order}, got {val!r}",
                                 f"{flag} needs {order.upper().replace('AND', 'and')} (mm), got {got}"))
    sp, org = np.asarray(spacing, float), np.asarray(origin, float)
    lo = org - 0.5 * sp
    hi = lo + np.asarray(shape, float) * sp
    tol = 1e-6 * sp
    box = np.array([v[0], v[1], v[2], v[3]]) if need == 4 else np.array([v[0], v[1], lo[1], hi[1]])
    if box[0] < lo[0] - tol[0] or box[1] > hi[0] + tol[0] or box[2] < lo[1] - tol[1] or box[3] > hi[1] + tol[1]:
        # a depth spans every line: only the axial extent is said (a convex frame's lines are arcs, not mm of y)
        extent = _extent_text(shape[:1] if need == 2 else shape, spacing, origin)
        raise InputError(f"{_given(what, v)} leaves the image; the image extent is {extent}")
    idx = []
    for k, axis in ((0, 0), (2, 1)):          # pixel centres c_i = origin + i * spacing inside [box_k, box_k+1]
        i0 = int(np.ceil((box[k] - org[axis]) / sp[axis] - 1e-6))
        i1 = int(np.floor((box[k + 1] - org[axis]) / sp[axis] + 1e-6)) + 1
        idx.append((max(0, i0), min(int(shape[axis]), i1)))
    if idx[0][1] - idx[0][0] < 2 or idx[1][1] - idx[1][0] < 2:
        # numbers in metres (a MATLAB script's): inside the image and a few pixels wide once read as mm
        big = np.r_[box[:2] * 1e3, box[2:] * (1e3 if need == 4 else 1.0)]
        metres = (big[0] >= lo[0] - tol[0] and big[1] <= hi[0] + tol[0] and big[2] >= lo[1] - tol[1]
                  and big[3] <= hi[1] + tol[1] and big[1] - big[0] >= 2 * sp[0] and big[3] - big[2] >= 2 * sp[1])
        mm = " ".join(f"{x * 1e3:g}" for x in v)
        hint = ("; the numbers look like metres: pass them in mm, "
                + pass_as(f"{what}=({mm.replace(' ', ', ')}) (CLI: --{what} {mm})", f"--{what} {mm}")
                if metres else "")
        raise InputError(f"{_given(what, v)} holds fewer than 2 x 2 pixels; the image extent "
                         f"is {_extent_text(shape, spacing, origin)}{hint}")
    region = EchoRegion(idx[0], idx[1], tuple(int(s) for s in shape), tuple(float(s) for s in sp),
                        tuple(float(s) for s in org), given=what)
    x0, x1, y0, y1 = region.roi_mm
    region.excluded = f"outside the given {what} x {x0:.1f}-{x1:.1f} mm, y {y0:.1f}-{y1:.1f} mm excluded"
    return region


#: The receiver noise of the frames :func:`femreg.register` registers after its crop (:func:`noise_share`), read
#: by its refinement stage (:func:`femreg.refine.noise_ncc`); None: unknown.  A context variable, not an argument
#: of the public ``register``: it describes the cut frames of one call, not a user's choice.
_NOISE_SHARE = contextvars.ContextVar("femreg_echo_noise_share", default=None)


def noise_share(region: EchoRegion, reference) -> float | None:
    """The receiver noise's mean envelope power over the mean envelope power of ``reference`` (the frame cut to
    the echo rectangle), where the detection left rows out at the noise floor (:attr:`EchoRegion.noise_seen`),
    else None.

    The floor is the median envelope power of the quietest rows; noise alone has a Rayleigh envelope, whose
    power's median is ln 2 times its mean (Goodman 2007, ch. 3).  A ratio of powers: the same after the
    registration normalises the frames."""
    if not region.noise_seen:
        return None
    env = envelope(np.asarray(reference, float))
    mean = float(np.mean(env * env))
    return 10.0 ** (region.floor_db / 10.0) / np.log(2.0) / mean if mean > 0 else None


@contextlib.contextmanager
def registering_crop(share):
    """Context in which :func:`crop_noise_share` is ``share`` (the registration of a crop's frames)."""
    token = _NOISE_SHARE.set(share)
    try:
        yield
    finally:
        _NOISE_SHARE.reset(token)


def crop_noise_share() -> float | None:
    """:func:`noise_share` of the crop being registered (:func:`registering_crop`), or None."""
    return _NOISE_SHARE.get()


class Crop:
    """The frames cut to a rectangle, and how to put a result registered there back on the full frames' pixel grid.

    A detected echo rectangle is cut as it is (the mesh margin lies inside it: no noise enters any stage); a given
    one is widened by the mesh margin where the image has it, so that the mesh covers it.  ``slices``: (rows,
    cols) of the frames kept; ``origin``: the crop's pixel [0, 0] centre (mm); ``region``: the
    :class:`EchoRegion`; ``seconds``: the detection's time."""

    def __init__(self, region: EchoRegion, margin_px, pad: bool, seconds=0.0):
        self.region = region
        n, m = region.shape
        (a, b), (c, d) = region.rows, region.cols
        mr, mc = (int(x) for x in margin_px)
        pr, pc = (mr, mc) if pad else (0, 0)
        self.slices = (slice(max(0, a - pr), min(n, b + pr)), slice(max(0, c - pc), min(m, d + pc)))
        self.origin = (region.origin[0] + self.slices[0].start * region.spacing[0],
                       region.origin[1] + self.slices[1].start * region.spacing[1])
        self.seconds = float(seconds)
        #: the fan (True) and the pixels of eq:IR (True) on the crop, for a :func:`fan_region`; else None
        self.inside = self.weights = self.rectangle = None
        if getattr(region, "fill", None) is not None:      # volumes' boxes (femreg.echo_volume) hold no fill
            self.inside = ~region.fill[self.slices]
            self.weights = fan_weights(region.fill, region.spacing)[self.slices]
            if region.rectangle is not None:    # the largest rectangle without fill, on the crop
                self.rectangle = tuple(slice(lo - s.start, hi - s.start)
                                       for (lo, hi), s in zip(region.rectangle, self.slices))
        for k, (s, mp) in enumerate(zip(self.slices, (mr, mc))):
            if s.stop - s.start - 2 * mp < 1:
                raise InputError(f"the {'region' if pad else 'echo region'} {region.roi_mm[2 * k]:.2f} to "
                                 f"{region.roi_mm[2 * k + 1]:.2f} mm is too small for a mesh inside the margin "
                                 f"({mp} pixels) along axis {k}" + (f": {region.excluded}" if region.excluded else ""))

    @property
    def roi_mm(self) -> tuple:
        return tuple(float(v) for v in self.region.roi_mm)

    @property
    def mask(self) -> DataMask | None:
        """The fan on the crop as the registration there takes it (``data_mask`` of :func:`femreg.register`),
        or None."""
        return None if self.inside is None else DataMask(self.inside, self.weights, self.rectangle)

    def frames(self, *images):
        """The images (volumes) cut to :attr:`slices` (views)."""
        return [np.asarray(f)[self.slices] for f in images]

    @staticmethod
    def _clear_grids(res):
        res._grid = res._grid_element = None

    def widen(self, res):
        """``res`` (a result on the crop) on the full frames' pixel grid, saying what was excluded (in place;
        idempotent); returns it."""
        res.shape = tuple(self.region.shape)
        res.origin = np.asarray(self.region.origin, float)
        self._clear_grids(res)                         # grid fields are recomputed on the full grid
        res.roi = self.roi_mm
        res.echo_region = self.region                  # what was cut, as data (femreg.geometry.beam_excluded)
        if self.region.excluded and getattr(res, "excluded", None) != self.region.excluded:
            res.excluded = self.region.excluded
            res.message = f"{res.message}; {self.region.excluded}" if res.message else self.region.excluded
        res.timings["echo"] = self.seconds
        if getattr(self.region, "fill", None) is not None:    # nothing reported outside the fan: regulariser's field
            res.data_mask = ~self.region.fill
        return res


def _nodal(spec) -> bool:
    """True for a nodal vector (an array over the default mesh's nodes, which a crop would change)."""
    return isinstance(spec, (np.ndarray, list, tuple))


def crop_request(roi, depth, mesh, initial, offset, *, volume: bool = False):
    """What :func:`crop_for` (and the volumes' :func:`femreg.echo_volume.crop_for_volume`) are asked: None when
    nothing is cropped (``roi`` and ``depth`` None, a user ``mesh``, or the detection with a nodal ``initial`` /
    ``offset`` of the default mesh), True for a given box or depth, False for the detection; the errors of a
    bad ``roi`` or of a box given with a user mesh."""
    if roi is None and depth is None:
        return None
    if isinstance(roi, str) and roi != "auto":
        box = "(x0, x1, y0, y1, z0, z1) mm for a volume" if volume else "(x0, x1, y0, y1) mm"
        raise InputError(f"roi must be 'auto', None or {box}, got {roi!r}")
    given = depth is not None or not isinstance(roi, str)
    if mesh is not None:
        if given:
            raise InputError("roi / depth and a user mesh exclude each other: the mesh defines the region")
        return None
    if not given and (_nodal(initial) or _nodal(offset)):
        return None
    return given


#: Share of a given rectangle's rows (or lines) of zero samples above which it is refused: nothing recorded there.
BLANK_REFUSED = 0.5


def _refuse_blank(region, ref, mov, what) -> None:
    """:class:`InputError` when more than :data:`BLANK_REFUSED` of the rows or of the lines of a user's rectangle
    hold only zero samples in either frame (below the recorded depth, blanked lines): a registration there fails
    on images that do not match (the in vivo frames' last 1.5 mm: NCC after -1.000, exit 1 before)."""
    (a, b), (c, d) = region.rows, region.cols
    for img, which in ((ref, "reference"), (mov, "moving")):
        crop = img[a:b, c:d]
        for axis, name in ((1, "rows"), (0, "lines")):
            blank = ~np.any(crop != 0, axis=axis)
            if blank.mean() > BLANK_REFUSED:
                raise InputError(f"the {what} given holds no signal: {int(blank.sum())} of {blank.size} {name} of the "
                                 f"{which} frame there are zero samples (nothing recorded); choose a region inside "
                                 f"the echo, or leave --roi / --depth out to have it found")


def crop_for(reference, moving, spacing, origin=(0.0, 0.0), *, roi="auto", depth=None, mesh=None,
             margin=None, initial=None, offset=None, fan=False, data_mask=None) -> Crop | None:
    """The crop :func:`femreg.register` / :func:`femreg.track` register on, or None for the whole frames.

    ``roi``: "auto" (default) detects the echo rectangle (:func:`find_echo`), None keeps the whole frames,
    (x0, x1, y0, y1) mm a given rectangle; ``depth`` (d0, d1) mm a given depth range over all lines (a given
    rectangle or depth disables the detection).  With a user ``mesh`` there is no crop (a given roi or depth is
    then an error), nor for the detection when ``initial`` or ``offset`` is a nodal vector of the default mesh.
    The detection changes nothing (None) when what it excludes lies within the mesh margin.  ``fan``: frames
    with fill (:func:`find_fill`) are cut to the bounding box of their fan instead of the largest rectangle,
    the crop's :attr:`Crop.inside` / :attr:`Crop.weights` saying where eq:IR holds (:func:`fan_region`).
    ``data_mask`` ((n_axial, n_lateral) bool, True where there are data): that fan instead of the detection (no
    fill, echo or noise floor is looked for; with a given ``roi`` or ``depth`` an :class:`InputError`), None when
    it is True everywhere."""
    given = crop_request(roi, depth, mesh, initial, offset)
    if data_mask is not None and given:
        raise InputError("give data_mask or roi / depth, not both (data_mask: the region registered is its "
                         "bounding box)")
    if given is None:
        return None
    t = time.perf_counter()
    ref = validate_image(reference, "reference image")
    mov = validate_image(moving, "moving image")
    if ref.shape != mov.shape:
        raise InputError(f"image shape mismatch: reference {ref.shape} vs moving {mov.shape}")
    spacing, origin = validate_spacing(spacing, origin)
    mp = _margin_pixels(margin, spacing)
    if data_mask is not None:
        mask = as_data_mask(data_mask, ref.shape, spacing)
        region = None if mask is None else given_fan(mask.inside, spacing, origin)
        return None if region is None else Crop(region, mp, False, time.perf_counter() - t)
    if given:
        region = region_from_mm(ref.shape, spacing, origin, roi=None if isinstance(roi, str) else roi, depth=depth)
        _refuse_blank(region, ref, mov, "roi" if depth is None else "depth")
        return Crop(region, mp, True, time.perf_counter() - t)
    if not rf_like(ref):
        region = find_fill(ref, mov, spacing, origin)
        if region is None:
            return None
        if fan:
            return Crop(fan_region(region), mp, False, time.perf_counter() - t)
    else:
        fan_rf = find_rf_fan(ref, mov, spacing, origin) if fan else None
        if fan_rf is not None:          # RF scan-converted onto a Cartesian grid: the fan, as a B-mode's
            return Crop(fan_region(fan_rf), mp, False, time.perf_counter() - t)
        region = _find_echo(ref, mov, spacing, origin)
    n, m = ref.shape
    (a, b), (c, d) = region.rows, region.cols
    if a <= mp[0] and b >= n - mp[0] and c <= mp[1] and d >= m - mp[1]:
        return None                  # nothing beyond the margin the mesh leaves out anyway
    return Crop(region, mp, False, time.perf_counter() - t)
