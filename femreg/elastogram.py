"""``femreg.elastogram``: a freehand cine loop -> the pairs worth registering -> normalised strain images ->
a persistent strain cine and one best elastogram.

Stages (plain data between them):

1. **Screen** every consecutive pair ``(k, k+1)`` fast: NCC block matching (:func:`femreg.blockmatch.block_match`,
   sub-sample peaks) of low-passed, decimated envelopes (:mod:`femreg.pyramid`: ~3 samples per speckle cell),
   each frame's envelope normalised to zero mean and unit variance, so a gain change does not matter.  The
   windows, decimation and search are sized from the speckle's own cell (:func:`femreg.speckle.speckle_cell`:
   a skin line or the echo's fall with depth widen the whole envelope's).  The least-squares affine fit of the
   window displacements gives the axial strain ``e_k = du_x/dx`` and the lateral
   shift; the median window NCC measures what the fit cannot explain: out-of-plane motion, decorrelation.
2. **Choose** pairs: for every frame ``i`` the later frame ``j`` (at most ``max_span`` frames on) whose accumulated
   strain ``prod(1 + e_k) - 1`` lies in the band and closest to its geometric centre; a candidate's quality is its
   worst consecutive NCC times a lateral factor (``1 - |shift| / max_lateral``) times a strain factor (1 at the
   band centre, 0 at its edges).  Candidates passing ``min_ncc`` are taken greedily by quality with
   non-overlapping frame intervals (each stretch of motion is used once), then screened directly (envelopes of
   ``i`` and ``j``), which must confirm the band and ``min_ncc``.
3. **Register** the chosen pairs with :func:`femreg.register` on one mesh (frame 0's default), each warm-started
   from the previous pair's field scaled to the new strain (plus the difference of the two screening affine
   fits); a failed warm start is redone from the pyramid.  A pair is usable when the registration succeeds and
   its mean axial strain lies in the band.
4. **Normalise** each strain image by its mean (normalised strain, sign-free: compression and release alike) and
   **combine** by quality-weighted persistence (Lindop et al. 2008, "An intelligent interface for freehand strain
   imaging", Ultrasound Med Biol 34:1117): ``D_k = (w_k s_k + rho W'_{k-1} D'_{k-1}) / (w_k + rho W'_{k-1})``,
   ``W_k = w_k + rho W'_{k-1}``, where ``'`` moves the previous image to the new reference frame (by the previous
   pair's registered field, then the screened motion), ``w_k = (e_k / e_c)^2 q_k^2 / (1 - q_k^2)`` per pixel
   (``q_k`` the element NCC after registration, ``e_c`` the band centre: the inverse strain-noise variance of
   :func:`_weight`).  The best elastogram is the cine frame of largest mean weight.

Envelope / B-mode loops in the fan of a scan-converted convex or phased array (fill fixed on the screen around
it, :func:`femreg.echo.find_fill`, or a given ``data_mask``) are taken whole, as :func:`femreg.register` takes them:
cut to the fan's bounding box, screened on the block-matching windows that see no fill (the affine fit and the
median NCC over those; windows on the wedges read no motion), registered with the fill weighted 0 in eq:IR, and
NaN outside the fan.  Measured (``benchmarks/elastogram_fan.py``, an L7 loop in a fan, 16 frames, seeds 5-7):
82 % of the fan covered at 15.0-17.4 % normalised strain error, against 35-36 % at 18.6-21.7 % on the largest
rectangle without fill.

Convex / phased-array loops in their native (range, angle) samples (``geometry=femreg.Convex(...)`` or
``femreg.Sector(...)``): the screening runs in sample space, each pair is registered in physical x, y
(:func:`femreg.geometry.register_beam`, one physical mesh), and the results are scan-converted onto a Cartesian
grid that holds the fan (docs/geometry.md, "Elastograms").

Units: strains are fractions (percent only in ``pairs.csv`` and messages), lengths mm, images (axial, lateral).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import time
from dataclasses import dataclass, field as dc_field, replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from ._atomic import atomic_savez, atomic_write_text, open_run_folder, progress_bar
from .blockmatch import block_match
from .echo import crop_for, find_rf_fan, rf_like
from .errors import InputError, pass_as
from . import orientation
from .image import repeated_frames, validate_image, validate_spacing
from .mesh import check_element_size, roi_mesh
from .pyramid import default_settings, element_rule, gaussian_decimate
from .registration import shared_search, sharing_start
from .speckle import envelope, speckle_cell, speckle_statistics

__all__ = ["elastogram", "ElastogramResult", "screen_pairs", "band_advice", "display_range", "DEFAULT_BAND",
           "PAIR_COLUMNS", "DISPLAY_PERCENTILES", "WEIGHTED_PERCENTILES", "saturated_fraction"]

#: Default band of axial strain magnitude (fraction) of the pairs registered.
DEFAULT_BAND = (0.005, 0.02)
#: Columns of ``pairs.csv``.
PAIR_COLUMNS = ("ref", "mov", "axial_strain_percent", "ncc", "quality", "selected")
#: Largest correlation the persistence weight believes: static near-field echoes (in vivo: NCC ~1 in the first
#: 2-3 mm) would otherwise outweigh the tissue 20-fold.
RHO_MAX = 0.98
#: Default persistence factor rho (weight of the previous cine frame).
DEFAULT_PERSISTENCE = 0.7
#: Percentiles of the normalised strain over the good-quality pixels that set the pictures' colour range
#: (:func:`display_range`).
DISPLAY_PERCENTILES = (2.0, 98.0)
#: Percentiles of the normalised strain over all covered pixels, weighted by their persistence weight, that the
#: colour range is widened to hold (:func:`display_range`): at most 1 % of the image's weight saturates at
#: either end.
WEIGHTED_PERCENTILES = (1.0, 99.0)


def _weighted_percentiles(x, w, percentiles):
    """Percentiles (0-100) of the values ``x`` weighted by ``w`` (both 1D, ``w`` > 0): the midpoint rule of the
    cumulative weight, linear between the sorted values."""
    order = np.argsort(x)
    x, w = x[order], w[order]
    c = np.cumsum(w)
    c = (c - 0.5 * w) / c[-1]
    return [float(np.interp(p / 100.0, c, x)) for p in percentiles]


def display_range(exx, quality, percentiles=DISPLAY_PERCENTILES, weighted=WEIGHTED_PERCENTILES) -> tuple:
    """Colour range ``(lo, hi)`` of a normalised strain image (mean 1): the ``percentiles`` of ``exx`` over the
    pixels whose ``quality`` (persistence weight, same shape) is at least its median over the covered pixels,
    widened to hold the ``weighted`` percentiles over every covered pixel weighted by its ``quality``, and 1
    (the mean).  A fixed 0-2 range saturated 31 % of the in vivo elastogram of seq299 (16 % above 2, 15 % below
    0); the good pixels alone left 17.4 % of seq304's saturated (its near field at 5-12 mm, of low but not
    negligible weight, read 3-8 x the mean), the weighted widening 7.6 % (seq299: 4.8 %, unchanged), while a
    decorrelated patch of negligible weight still cannot set it.  (0, 2) when no pixel is covered."""
    e = np.asarray(exx, float)
    q = np.broadcast_to(np.asarray(quality, float), e.shape)
    ok = np.isfinite(e) & np.isfinite(q) & (q > 0)
    if not ok.any():
        return 0.0, 2.0
    good = ok & (q >= np.median(q[ok]))
    lo, hi = (float(v) for v in np.percentile(e[good if good.any() else ok], percentiles))
    if weighted is not None:
        wlo, whi = _weighted_percentiles(e[ok], q[ok], weighted)
        lo, hi = min(lo, wlo), max(hi, whi)
    lo, hi = min(lo, 1.0), max(hi, 1.0)
    if not hi > lo:
        lo, hi = lo - 0.5, hi + 0.5
    return lo, hi


def saturated_fraction(exx, quality, strain_range) -> float:
    """Fraction of the covered pixels (finite ``exx``, ``quality`` > 0) whose normalised strain lies outside
    ``strain_range`` (lo, hi): drawn in the colour of the nearer end.  NaN when no pixel is covered."""
    e = np.asarray(exx, float)
    q = np.broadcast_to(np.asarray(quality, float), e.shape)
    ok = np.isfinite(e) & np.isfinite(q) & (q > 0)
    if not ok.any():
        return float("nan")
    lo, hi = strain_range
    return float(np.mean((e[ok] < lo) | (e[ok] > hi)))


@dataclass
class ElastogramResult:
    """Outcome of :func:`elastogram`.

    Attributes
    ----------
    exx : (n_axial, n_lateral) float
        Best elastogram: normalised axial strain (mean 1, sign-free) on the pixel grid of frame ``ref_frame``,
        NaN where no pair covers.
    quality : (n_axial, n_lateral) float
        Its persistence weight ``W`` (0 where not covered).
    ref_frame : int; spacing, origin : (2,) mm (of the registered rectangle)
    region : ((r0, r1), (c0, c1)) or None
        The rectangle of the input frames (pixel ranges, half-open) the loop was screened and registered on: a
        given ``roi`` / ``depth`` (widened by the mesh margin), the echo rectangle of RF frames
        (:func:`femreg.echo.find_echo`, as :func:`femreg.register` and :func:`femreg.track` detect it with
        ``roi="auto"``: the noise floor, dead lines, saturation left out; noise a time-gain compensation lifts
        at depth, where the frames do not match), or the bounding box of the fan when envelope / B-mode frames
        hold fill (:func:`femreg.echo.find_fill`: the wedges of a scan-converted sector, fixed on
        the screen while the tissue moves) or a ``data_mask`` is given; None: the whole frames.  ``excluded``
        says what was left out.
    data_mask : (n_axial, n_lateral) bool or None
        On the grid of ``exx``: True in the fan (``exx`` NaN and ``quality`` 0 outside it); None without a fan.
    cine : (n_cine, n_rows, n_lateral) float32
        Persistent normalised strain after each usable pair on every ``q``-th pixel row (``cine_spacing`` (2,) mm;
        ``q`` about a third of the axial speckle cell); ``cine_frames`` their reference frames.
    pairs : list of dict
        One row per candidate pair (keys :data:`PAIR_COLUMNS` plus ``registered``, ``usable``, ``message``).
    screen : dict
        Consecutive-pair screening: ``strain``, ``lateral_mm``, ``ncc`` (each (n - 1,)).
    timings : dict, seconds per stage.
    repeated : list of int
        Frames k whose samples equal frame k - 1's (written twice by the scanner or the export): no motion between
        them, so a pair ending on one is the pair ending on the frame before, and a pair starting on one is no
        candidate of its own (``pairs`` holds none: the pair starting on the frame before covers it).
    geometry : femreg.Convex | femreg.Sector or None
        The probe of a loop of (range, angle) frames: ``exx``, ``quality``, ``cine`` and ``data_mask`` are then
        scan-converted onto a Cartesian grid (``spacing``, ``origin``: x depth, y lateral, mm;
        :func:`femreg.geometry.frame_grid`), the strain the physical axial one; None: a linear array's frames.
    sample_spacing, sample_origin : (2,) or None
        With a ``geometry``: the registered frames' range step (mm) and angle pitch (deg), and their first range
        (mm) and 0, as :func:`femreg.register` takes them (after a ``depth`` cut).
    """

    exx: np.ndarray
    quality: np.ndarray
    ref_frame: int
    spacing: np.ndarray
    origin: np.ndarray
    cine: np.ndarray
    cine_frames: list
    pairs: list
    screen: dict
    cine_spacing: np.ndarray = None
    timings: dict = dc_field(default_factory=dict)
    region: tuple | None = None
    excluded: str | None = None
    data_mask: np.ndarray | None = None
    repeated: list = dc_field(default_factory=list)
    geometry: object = None
    sample_spacing: tuple | None = None
    sample_origin: tuple | None = None

    @property
    def n_usable(self) -> int:
        return sum(1 for p in self.pairs if p["usable"])

    def to_grid(self, values, step: int = 1) -> np.ndarray:
        """``values`` on the registered frames' pixels (the input frames cut to ``region``; (n_axial,
        n_lateral)) -> on the grid of ``exx`` (``step`` = the cine's row step: on the grid of ``cine``), e.g. a
        B-mode to draw beside it; with a ``geometry`` scan-converted (:func:`femreg.geometry.to_cartesian`, NaN
        outside the fan), else every ``step``-th row as it is."""
        v = np.asarray(values, float)
        if self.geometry is None:
            return v[::step]
        from .geometry import frame_grid, to_cartesian

        dr, r0 = float(self.sample_spacing[0]), float(self.sample_origin[0])
        return to_cartesian(v, self.geometry, dr, r0, _row_grid(frame_grid(self.geometry, v.shape, dr, r0), step))


def _row_grid(grid, step):
    """Every ``step``-th row of a Cartesian ``grid`` (:func:`femreg.geometry.frame_grid`): the cine's."""
    (nx, ny), (dx, dy), origin = grid
    return (len(range(0, nx, step)), ny), (step * dx, dy), origin


# -- screening -----------------------------------------------------------------------------------------------

class _Screener:
    """Decimated, normalised envelopes of the frames (computed once each) and envelope block matching."""

    def __init__(self, frame0, spacing, origin, regularizer, mask=None):
        # a fan's speckle from its largest rectangle without fill (as femreg.register)
        part = frame0 if mask is None or mask.rectangle is None else frame0[mask.rectangle]
        #: the first frame's speckle statistics (:func:`femreg.speckle.speckle_statistics`), a fan's without fill
        self.stats = stats = speckle_statistics(part, spacing)
        # the speckle's own cell: the whole envelope's also reads a bright skin line and the brightness falling
        # with depth (a 12.5 MHz loop without TGC: 1.23 x 7.8 mm for 0.12 x 0.4 mm), which decimated by 21 rows
        # and matched 10 mm windows over 15 mm of lateral search (step strains 0.31 % read 0.73 %)
        own = speckle_cell(part, spacing, stats=stats)
        cell = np.where(np.isfinite(own), np.fmin(own, stats.cell), stats.cell)
        st = default_settings(part.shape, spacing, replace(stats, cell=cell), **element_rule(regularizer))
        self.q, self.ql = int(st.decimation), int(st.lateral_decimation)
        self.spacing = np.asarray(spacing, float) * (self.q, self.ql)
        self.origin = np.asarray(origin, float)
        self.extent = np.asarray(frame0.shape) * np.asarray(spacing, float)
        # windows of ~8 x 3 speckle cells (as the pyramid's local search), search 3 x 2 cells plus the motion a
        # 3 % strain makes at the bottom of the image
        self.window = np.minimum(np.maximum([8.0 * cell[0], 3.0 * cell[1]], self.extent / [12.0, 8.0]),
                                 self.extent / 2.0)
        self.search = np.array([3.0 * cell[0] + 0.03 * self.extent[0], 2.0 * cell[1]])
        self._cache = {}
        #: True on the decimated grid where a window sees no fill (the fan's eq:IR weights over the filter's
        #: support); None: everywhere
        self.keep = None
        if mask is not None:
            w = ndimage.minimum_filter(np.asarray(mask.weights, np.uint8), size=(2 * self.q + 1, 2 * self.ql + 1),
                                       mode="nearest")
            self.keep = w[::self.q, ::self.ql].astype(bool)

    def env(self, k, frame):
        e = self._cache.get(k)
        if e is None:
            e = envelope(frame)
            if self.ql > 1:
                e = gaussian_decimate(e, self.ql, 1)
            if self.q > 1:
                e = gaussian_decimate(e, self.q, 0)
            e = (e - e.mean()) / (e.std() or 1.0)
            if len(self._cache) > 64:
                self._cache.pop(next(iter(self._cache)))
            self._cache[k] = e
        return e

    def match(self, ea, eb):
        """Affine coefficients (3, 2), axial strain, lateral shift (mm, at the image centre), median NCC."""
        bm = block_match(ea, eb, self.spacing, self.origin, window=self.window, overlap=(0.5, 0.5),
                         search=self.search, median_size=3, subsample=True, compand_strain=None)
        coef, ncc = bm.affine_fit(), bm.ncc
        inside = self._inside(bm, ea.shape)
        if inside is not None:
            coef, ncc = self._fan_fit(bm, inside, coef)
        centre = self.origin + 0.5 * self.extent
        lateral = float(coef[0, 1] + coef[1, 1] * centre[0] + coef[2, 1] * centre[1])
        return coef, float(coef[1, 0]), lateral, float(np.median(ncc))

    def _inside(self, bm, shape):
        """(na, nl) bool: the windows of ``bm`` (on the decimated grid of ``shape``) that see no fill, or None
        without a fan.  Their starts as :func:`femreg.blockmatch.block_match` places them."""
        if self.keep is None:
            return None
        w = np.minimum(shape, np.maximum(2, np.round(self.window / self.spacing).astype(int)))
        ia = np.rint((bm.x - self.origin[0]) / self.spacing[0] - (w[0] - 1) / 2.0).astype(int)
        il = np.rint((bm.y - self.origin[1]) / self.spacing[1] - (w[1] - 1) / 2.0).astype(int)
        K = np.zeros((shape[0] + 1, shape[1] + 1))
        K[1:, 1:] = np.cumsum(np.cumsum(self.keep, 0), 1)          # fill-free pixels per window, from sums
        A, L = np.meshgrid(ia, il, indexing="ij")
        n = K[A + w[0], L + w[1]] - K[A, L + w[1]] - K[A + w[0], L] + K[A, L]
        return n >= w[0] * w[1]

    @staticmethod
    def _fan_fit(bm, inside, coef):
        """Affine coefficients and window NCCs of the fill-free windows: their raw peaks median-filtered (3 x 3)
        over fill-free neighbours only (a window on the fixed wedge reads no motion); the whole grid's ``coef``
        when they do not determine an affine field."""
        na, nl = inside.shape
        raw = np.pad(np.where(inside[..., None], bm.raw, np.nan), ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
        near = np.stack([raw[i:i + na, j:j + nl] for i in range(3) for j in range(3)])[:, inside]
        filt = np.nanmedian(near, axis=0)         # (n_inside, 2); each holds its own window
        X, Y = np.meshgrid(bm.x, bm.y, indexing="ij")
        G = np.column_stack([np.ones(X.size), X.ravel(), Y.ravel()])[inside.ravel()]
        if np.unique(G[:, 1]).size < 3 or np.unique(G[:, 2]).size < 3:
            return coef, bm.ncc
        fit, _, rank, _ = np.linalg.lstsq(G, filt, rcond=None)
        return (fit, bm.ncc[inside]) if rank == 3 else (coef, bm.ncc)


def _band(band):
    try:
        lo, hi = (float(b) for b in band)
    except (TypeError, ValueError):
        raise InputError(f"band must be two strains (lo, hi) as fractions, got {band!r}") from None
    if not (0 < lo < hi < 0.2):
        raise InputError(f"band must satisfy 0 < lo < hi < 0.2 (fractions: 0.005 = 0.5 %), got {band!r}")
    return lo, hi


def band_advice(screen: dict, band=DEFAULT_BAND, max_span: int = 8, cli: bool = False) -> str:
    """Why no pair of a loop fell in the strain band, from the consecutive screening (``ElastogramResult.screen``),
    and what to pass instead: the largest strain any pair at most ``max_span`` frames apart reaches (accumulated as
    :func:`screen_pairs` does), or the smallest consecutive strain when every step overshoots; "" when the band
    was reachable (the pairs in it then failed their NCC or registration).  ``cli``: the advice in the command's
    flags only (``--band``, ``--resume``, ``--max-span``)."""
    lo, hi = _band(band)
    e = np.asarray(screen.get("strain", ()), float)
    if e.size == 0 or not np.all(np.isfinite(e)):
        return ""
    best, where = 0.0, (0, 1)
    for i in range(e.size):
        acc = np.cumprod(1.0 + e[i:i + int(max_span)]) - 1.0
        k = int(np.argmax(np.abs(acc)))
        if abs(acc[k]) > abs(best):
            best, where = float(acc[k]), (i, i + k + 1)
    if abs(best) < lo:
        lo_new = max(0.05, np.floor(abs(best) * 0.8 * 2000) / 20)        # percent, 0.05 % steps, below the largest
        how = (f"--band {lo_new:g} {100 * hi:g} (with --resume the screening is kept)" if cli else
               f"band=({lo_new / 100:g}, {hi:g}) (CLI: --band {lo_new:g} {100 * hi:g}; with resume=True, "
               f"--resume, the screening is kept)")
        longer = "--max-span" if cli else "max_span, --max-span"
        return (f"the loop compresses less than the band: the largest axial strain between frames at most "
                f"{int(max_span)} apart is {100 * best:+.2f} % (frames {where[0]} -> {where[1]}); lower the band, "
                f"e.g. {how}" + (f", or allow longer spans ({longer})" if e.size > int(max_span) else ""))
    small = float(np.min(np.abs(e)))
    if small > hi:
        hi_new = min(19.0, np.ceil(small * 1.25 * 200) / 2)                # percent, 0.5 % steps, above the smallest
        how = (f"--band {100 * lo:g} {hi_new:g}" if cli else
               f"band=({lo:g}, {hi_new / 100:g}) (CLI: --band {100 * lo:g} {hi_new:g})")
        return (f"every consecutive pair strains more than the band: the smallest axial strain is "
                f"{100 * small:.2f} %; raise the band, e.g. {how}, or record at a higher frame rate")
    return ""


def _strain_factor(e, lo, hi):
    c = np.sqrt(lo * hi)
    return float(max(0.0, 1.0 - abs(np.log(abs(e) / c)) / np.log(hi / c))) if e != 0 else 0.0


def screen_pairs(strain, lateral, ncc, *, band=DEFAULT_BAND, max_span=8, min_ncc=0.6, max_lateral_mm=1.0,
                 repeated=()):
    """Candidate pairs from the consecutive screening (stage 2 of the module docstring, before the direct check).

    Parameters: ``strain``, ``lateral``, ``ncc`` (n - 1,) of the consecutive pairs; ``repeated`` the frames that
    repeat the one before (:func:`femreg.image.repeated_frames`): a pair starting on one is the pair starting on
    the frame before, so it is no candidate of its own.  Returns a list of dict rows ``ref, mov, strain
    (fraction), lateral_mm, ncc, quality, selected`` (selected: bool, greedy by quality with non-overlapping
    intervals), none starting on a repeated frame."""
    lo, hi = _band(band)
    c = np.sqrt(lo * hi)
    n = len(strain) + 1
    rows = []
    skip = set(int(k) for k in repeated)
    for i in range(n - 1):
        if i in skip:               # the same images as frame i - 1: its candidate covers this one
            continue
        acc, lat, worst, best = 1.0, 0.0, 1.0, None
        for j in range(i + 1, min(n, i + 1 + int(max_span))):
            acc *= 1.0 + strain[j - 1]
            lat += lateral[j - 1]
            worst = min(worst, ncc[j - 1])
            e = acc - 1.0
            if lo <= abs(e) <= hi and (best is None or abs(np.log(abs(e) / c)) < abs(np.log(abs(best[1]) / c))):
                best = (j, e, lat, worst)
            if abs(e) > hi:
                break
        if best is None:
            j = i + 1
            best = (j, float(strain[i]), float(lateral[i]), float(ncc[i]))
        j, e, lat, worst = best
        lat_f = max(0.0, 1.0 - abs(lat) / max_lateral_mm)
        q = float(max(worst, 0.0) * lat_f * _strain_factor(e, lo, hi))
        rows.append(dict(ref=i, mov=int(j), strain=float(e), lateral_mm=float(lat), ncc=float(worst), quality=q,
                         selected=False))
    used = np.zeros(n, bool)              # frame steps (k, k+1) already in a chosen pair
    for r in sorted(rows, key=lambda r: -r["quality"]):
        if r["quality"] <= 0 or r["ncc"] < min_ncc or not lo <= abs(r["strain"]) <= hi:
            continue
        if used[r["ref"]:r["mov"]].any():   # a later pair may start where this one ends
            continue
        r["selected"] = True
        used[r["ref"]:r["mov"]] = True
    return rows


# -- combination ---------------------------------------------------------------------------------------------

def _affine_disp(coef, shape, spacing, origin):
    x = origin[0] + spacing[0] * np.arange(shape[0])
    y = origin[1] + spacing[1] * np.arange(shape[1])
    X, Y = np.meshgrid(x, y, indexing="ij")
    return [coef[0, c] + coef[1, c] * X + coef[2, c] * Y for c in range(2)]


def _move(images, coef, spacing, origin, field=None):
    """Images on frame a's grid -> frame b's grid, ``x_b = x_a + u(x_a)``: the value at ``x_b`` is the image at
    ``x_a``, found by fixed-point iteration ``x_a = x_b - u(x_a)``; bilinear, 0 outside.  ``u`` is the
    registered field ``field`` = (ux, uy) on frame a's pixels (NaN outside its mesh) where given, plus the
    affine ``coef``; the affine alone elsewhere."""
    shape = images[0].shape
    ax, ay = _affine_disp(coef, shape, spacing, origin)
    if field is None:
        ux, uy = ax, ay
    else:
        ux, uy = (np.where(np.isfinite(f), f, 0.0) + a for f, a in zip(field, (ax, ay)))
    ii, jj = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    fi, fj = ii - ux / spacing[0], jj - uy / spacing[1]
    if field is not None:
        for _ in range(1):         # u changes by |grad u| |u| ~ 1e-2 x 0.2 mm over one step: one is enough
            vx = ndimage.map_coordinates(ux, [fi, fj], order=1, mode="nearest")
            vy = ndimage.map_coordinates(uy, [fi, fj], order=1, mode="nearest")
            fi, fj = ii - vx / spacing[0], jj - vy / spacing[1]
    return [ndimage.map_coordinates(im, [fi, fj], order=1, mode="constant", cval=0.0) for im in images]


def _to_pixel_rows(strain, weight, shape, step):
    """Normalised strain and persistence weight on every ``step``-th pixel row, each (n_rows, n_lateral), to every
    pixel row of ``shape`` by linear interpolation between the rows, the strain weighted.  Rows without weight
    (outside the mesh) are filled from the nearest covered row first: interpolating towards their zero weight
    drew a ramp of low weight along the mesh's top and bottom edges (a line on the quality picture).  Pixels
    nearer an uncovered row than a covered one get weight 0."""
    W = np.asarray(weight, float)
    D = np.where(W > 0, np.nan_to_num(np.asarray(strain, float)), 0.0)
    covered = W > 0
    if covered.any() and not covered.all():
        idx = ndimage.distance_transform_edt(~covered, return_distances=False, return_indices=True)
        Wf, WDf = W[tuple(idx)], (W * D)[tuple(idx)]
    else:
        Wf, WDf = W, W * D
    ii, jj = np.meshgrid(np.arange(shape[0]) / step, np.arange(shape[1]), indexing="ij")
    WD, Q = (ndimage.map_coordinates(a, [ii, jj], order=1, mode="nearest") for a in (WDf, Wf))
    near = ndimage.map_coordinates(covered.astype(float), [ii, jj], order=0, mode="nearest") > 0.5
    Q = np.where(near, Q, 0.0)
    return np.where(Q > 0, WD / np.where(Q > 0, Q, 1.0), np.nan), Q


def _weight(rho, strain_ratio):
    """Inverse strain-noise variance (up to a constant): the Cramer-Rao bound of time-delay estimation (Walker and
    Trahey 1995, IEEE UFFC 42:301) gives a delay variance proportional to ``1 / rho**2 - 1`` (``rho`` the
    correlation after registration, at most :data:`RHO_MAX`), and the strain noise scales with the delay noise over
    the strain."""
    r = np.clip(np.asarray(rho, float), 0.0, RHO_MAX)
    return strain_ratio ** 2 * r ** 2 / (1.0 - r ** 2)


def _pixel_quality(res, step):
    """Element NCC after registration (clipped to [0, 1]) averaged to the nodes and interpolated bilinearly to the
    pixels of every ``step``-th row (NaN outside the mesh)."""
    from scipy.interpolate import RegularGridInterpolator

    q = np.clip(np.nan_to_num(np.asarray(res.quality, float), nan=0.0), 0.0, 1.0)
    t, p = res.mesh.t, res.mesh.p
    acc = np.bincount(t.ravel(), weights=np.tile(q, t.shape[0]), minlength=p.shape[1])   # t: (4, n_elements)
    qn = acc / np.maximum(np.bincount(t.ravel(), minlength=p.shape[1]), 1)
    x = res.origin[0] + res.spacing[0] * np.arange(0, res.shape[0], step)
    y = res.origin[1] + res.spacing[1] * np.arange(res.shape[1])
    xs, ys = np.unique(p[0]), np.unique(p[1])
    if xs.size * ys.size == p.shape[1]:             # tensor-product mesh (the default ROI mesh)
        V = np.full((xs.size, ys.size), np.nan)
        V[np.searchsorted(xs, p[0]), np.searchsorted(ys, p[1])] = qn
        X, Y = np.meshgrid(x, y, indexing="ij")
        f = RegularGridInterpolator((xs, ys), V, bounds_error=False, fill_value=np.nan)
        return f(np.column_stack([X.ravel(), Y.ravel()])).reshape(X.shape)
    # any other mesh (a convex / sector frame's annular one): at the pixels' (samples') physical positions
    from .sampling import sample_points

    vec = np.zeros(2 * p.shape[1])
    vec[0::2] = qn
    pts = res.pixel_points().reshape(tuple(res.shape) + (2,))[::step].reshape(-1, 2)
    return sample_points(vec, res.locator, pts, ("ux",))[:, 0].reshape(-1, res.shape[1])


# -- the work of stages 1 and 3, in this process or on Dask workers --------------------------------------------

def _screen_run(scr, frame, k0, k1):
    """Consecutive screening of the pairs (k, k + 1), k0 <= k < k1: affine coefficients (k1 - k0, 3, 2), axial
    strain, lateral shift (mm) and NCC (each (k1 - k0,)); ``frame(k)`` gives frame k as float."""
    m = k1 - k0
    coef, e, lat, ncc = np.zeros((m, 3, 2)), np.zeros(m), np.zeros(m), np.zeros(m)
    for k in range(k0, k1):
        coef[k - k0], e[k - k0], lat[k - k0], ncc[k - k0] = scr.match(scr.env(k, frame(k)),
                                                                      scr.env(k + 1, frame(k + 1)))
    return coef, e, lat, ncc


def _stored_frames(path):
    """``frame(k)`` of the frames a worker reads from the .npy file of :func:`_pool` (memory-mapped)."""
    arr = np.load(path, mmap_mode="r")
    return lambda k: np.asarray(arr[k], dtype=float)


def _screen_task(scr, path, k0, k1):
    """:func:`_screen_run` on a worker, the frames read from ``path``."""
    return _screen_run(scr, _stored_frames(path), k0, k1)


def _direct_task(scr, path, pairs):
    """The direct screening of ``pairs`` [(i, j)] on a worker: [(coef, strain, lateral, ncc)]."""
    frame = _stored_frames(path)
    return [scr.match(scr.env(i, frame(i)), scr.env(j, frame(j))) for i, j in pairs]


def _verdict(rec, lo, hi):
    """(usable, message) of a registered pair: it succeeded and its mean axial strain lies in the band."""
    ms = rec["mean_strain"]
    if not rec["success"]:
        return False, f"registration failed: {rec['message']}"
    if not (np.isfinite(ms) and lo <= abs(ms) <= hi):
        return False, f"registered mean axial strain {100 * ms:.2f} % outside the band"
    return True, ""


def _register_run(frame, pairs, mesh, qa, band, out, resume, reg_args, on_rec=None, lattice=None):
    """Register ``pairs`` [(i, j, screened strain, screened affine coef (3, 2))] in order, each warm-started from
    the last usable one (module docstring, stage 3); ``frame(k)`` gives frame k as float.  Returns
    ``{(i, j): rec}`` (rec: exx, ux, uy on every ``qa``-th row, quality, mean_strain, success, ncc_after,
    message, u); ``on_rec(i, j, rec)`` after each.  ``out``: folder of the per-pair files (kept with
    ``resume``).  ``lattice``: ``(mesh_s, geometry, rho_c)`` of convex / sector frames, ``mesh`` being
    ``mesh_s`` (sample space, where the screening's affine fits hold) mapped to physical x, y."""
    from .registration import register

    lo, hi = band
    nodes = mesh.p.T if lattice is None else lattice[0].p.T

    def physical(v):        # a sample-space nodal displacement as the physical mesh's
        if lattice is None:
            return v
        from .geometry import to_physical_displacement

        return to_physical_displacement(lattice[0], v, lattice[1], lattice[2])

    per_pair = {}
    prev = None                      # (u, strain, coef) of the last good registration
    for i, j, strain, coef in pairs:
        path = None if out is None else Path(out) / "pairs" / f"pair_{i:05d}_{j:05d}.npz"
        if resume and path is not None and path.exists():
            with np.load(path, allow_pickle=False) as z:
                rec = {k: z[k] for k in z.files}
            rec = dict(exx=np.asarray(rec["exx"], float)[::qa], quality=np.asarray(rec["quality"], float),
                       ux=np.asarray(rec["ux"], float), uy=np.asarray(rec["uy"], float),
                       mean_strain=float(rec["mean_strain"]), success=bool(rec["success"]),
                       ncc_after=float(rec["ncc_after"]), message=str(rec["message"]), u=rec["u"])
        else:
            res = None
            s = strain / prev[1] if prev is not None and prev[1] != 0 else 0.0
            if 0.2 <= abs(s) <= 5.0:        # release mirrors compression: a negative scale is a start too
                A_now = np.column_stack([coef[0, c] + nodes @ coef[1:, c] for c in range(2)])
                A_prev = np.column_stack([prev[2][0, c] + nodes @ prev[2][1:, c] for c in range(2)])
                u0 = s * prev[0] + physical((A_now - s * A_prev).ravel())
                res = register(frame(i), frame(j), mesh=mesh, initial=u0, **reg_args)
                if not res.success:
                    res = None
            if res is None:
                res = register(frame(i), frame(j), mesh=mesh, **reg_args)
            g = res.on_grid()
            exx = g["exx"]
            if reg_args.get("data_mask") is not None:       # a fan: nothing outside it (the regulariser's field)
                exx = np.where(reg_args["data_mask"].inside, exx, np.nan)
            rec = dict(exx=exx[::qa], quality=_pixel_quality(res, qa), mean_strain=float(np.nanmean(exx)),
                       ux=g["ux"][::qa], uy=g["uy"][::qa],
                       success=bool(res.success), ncc_after=float(res.ncc_after), message=res.message,
                       u=res.u)
            if path is not None:
                atomic_savez(path, exx=exx.astype(np.float32), quality=rec["quality"].astype(np.float32),
                             ux=rec["ux"].astype(np.float32), uy=rec["uy"].astype(np.float32), row_step=qa,
                             mean_strain=rec["mean_strain"], success=rec["success"], ncc_after=rec["ncc_after"],
                             message=np.str_(rec["message"]), u=res.u, ref=i, mov=j)
        if _verdict(rec, lo, hi)[0]:
            prev = (np.asarray(rec["u"], float), rec["mean_strain"], coef)
        per_pair[(i, j)] = rec
        if on_rec is not None:
            on_rec(i, j, rec)
    return per_pair


def _register_task(path, pairs, mesh, qa, band, out, resume, reg_args, lattice=None, handed=None):
    """:func:`_register_run` on a worker, the frames read from ``path``; ``handed``: the start's search the cut
    decision made on the first pair (:func:`femreg.registration.shared_search`), taken by that pair's registration
    if it is this run's (a worker does not see the caller's context)."""
    with sharing_start(handed):
        return _register_run(_stored_frames(path), pairs, mesh, qa, band, out, resume, reg_args, lattice=lattice)


def _check_workers(workers, client):
    """Number of parallel tasks: the client's workers, else ``workers`` (an integer >= 1)."""
    if client is not None:
        return max(1, len(client.scheduler_info().get("workers", {})))
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise InputError(pass_as(f"workers must be an integer >= 1, got {workers!r}",
                                 f"--workers must be an integer >= 1, got {workers!r}"))
    return int(workers)


@contextlib.contextmanager
def _pool(n_workers, client, seq):
    """``(client, path)`` for the block: ``client`` itself, else a local Dask cluster of ``n_workers`` processes
    (``(None, None)`` for 1), and the frames ``seq`` stacked in one temporary .npy file that the workers map
    (sending them with every task costs more than the screening: 0.6 MB a frame)."""
    if client is None and n_workers <= 1:
        yield None, None
        return
    import tempfile

    with contextlib.ExitStack() as stack:
        if client is None:
            from .batch.engine import open_client

            client = stack.enter_context(open_client(n_workers))
        tmp = stack.enter_context(tempfile.TemporaryDirectory(prefix="femreg-elastogram-"))
        path = str(Path(tmp) / "frames.npy")
        np.save(path, np.stack([np.asarray(f) for f in seq]))
        yield client, path


def _chunks(n, parts):
    """At most ``parts`` contiguous (start, stop) ranges covering range(n), sizes differing by at most one."""
    parts = max(1, min(int(parts), n))
    edges = np.linspace(0, n, parts + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


# -- the entry point -----------------------------------------------------------------------------------------

def _validate(frames):
    if isinstance(frames, np.ndarray):
        if frames.ndim != 3:
            raise InputError(f"frames must be a 3D array (n_frames, n_axial, n_lateral), got ndim={frames.ndim}")
        seq = frames
    else:
        seq = list(frames)
        if not seq:
            raise InputError("need at least 3 frames for an elastogram, got 0")
    if len(seq) < 3:
        raise InputError(f"need at least 3 frames for an elastogram, got {len(seq)}")
    shape = np.shape(seq[0])
    for k in range(len(seq)):
        if np.shape(seq[k]) != shape:
            raise InputError(f"all frames must have the same shape: frame 0 {shape}, frame {k} {np.shape(seq[k])}")
        validate_image(seq[k], f"frame {k}")
    return seq


def _row_csv(rows):
    lines = [",".join(PAIR_COLUMNS)]
    for r in rows:
        lines.append(f"{r['ref']},{r['mov']},{100 * r['strain']:.4f},{r['ncc']:.4f},{r['quality']:.4f},"
                     f"{int(bool(r['usable']))}")
    return "\n".join(lines) + "\n"


def _cut(seq, crop):
    """``(frames, region, origin, excluded)``: the loop cut to ``crop`` (:func:`femreg.echo.crop_for`), its
    half-open pixel ranges ((r0, r1), (c0, c1)) in the input frames, the cut's origin (mm) and what it left out."""
    (a, b), (c, d) = region = tuple((s.start, s.stop) for s in crop.slices)
    seq = seq[:, a:b, c:d] if isinstance(seq, np.ndarray) else [np.asarray(f)[a:b, c:d] for f in seq]
    return seq, region, np.asarray(crop.origin, float), crop.region.excluded


def _beam(geometry, data_mask, roi):
    """The convex / sector geometry of a loop (:func:`femreg.probes.as_geometry`), or None for a linear array's;
    an :class:`InputError` for what it does not go with."""
    if geometry is None:
        return None
    from .probes import Convex, as_geometry

    beam = as_geometry(geometry)
    if beam is None:
        return None
    if not isinstance(beam, Convex):
        raise InputError("a femreg.Swept geometry is a swept probe's volumes: an elastogram takes the frames of a "
                         "linear, convex or phased array")
    if data_mask is not None:
        raise InputError("data_mask is on a Cartesian pixel grid: not with a convex / sector geometry")
    if roi is not None and not isinstance(roi, str):
        raise InputError(pass_as(f"roi {roi!r} is a Cartesian rectangle: with a {beam.kind} geometry give depth="
                                 "(d0, d1), a range along the rays in mm",
                                 f"--roi is a Cartesian rectangle: with --geometry {beam.kind} give --depth D0 D1 "
                                 "(a range along the rays, mm) instead"))
    return beam


def _positive_number(v) -> bool:
    if isinstance(v, (str, bool, np.bool_)):
        return False
    try:
        f = float(v)
    except (TypeError, ValueError):
        return False
    return bool(np.isfinite(f) and f > 0)


@sharing_start()    # a pair registered in this process takes the start the noise-at-depth decision made on it
def elastogram(frames, *, spacing, origin=(0.0, 0.0), band=DEFAULT_BAND, min_ncc: float = 0.6,
               max_lateral_mm: float | None = None, max_span: int = 8, persistence: float = DEFAULT_PERSISTENCE,
               output_dir=None, resume: bool = False, progress: bool = False, regularizer="momentum-stress",
               alpha=None, on_pair=None, workers: int = 1, client=None, data_mask=None, geometry=None,
               **register_kwargs) -> ElastogramResult:
    """Cine loop -> normalised-strain cine and best elastogram (module docstring).

    Parameters
    ----------
    frames : (n, n_axial, n_lateral) array or sequence of 2D frames (n >= 3; any real dtype, any gain)
    spacing, origin : (2,) mm
    band : (lo, hi)
        Axial strain magnitudes (fractions) of the pairs to register (default 0.5-2 %).
    min_ncc : float
        Least envelope NCC (screening) of a pair; lower means out-of-plane motion or decorrelation.
    max_lateral_mm : float, optional
        Largest lateral motion between the frames of a pair (default: a tenth of the image width).
    max_span : int
        Largest ``j - i`` of a pair.
    persistence : float in [0, 1)
        rho of the persistence (0: every cine frame is its own pair).
    output_dir : path, optional
        Per-pair results (``pairs/pair_IIIII_JJJJJ.npz``) and the screening (``screen.npz``), each written
        atomically when computed; with ``resume=True`` what is there is kept, not recomputed.  A resume that
        changes only how pairs are chosen (``band``, ``min_ncc``, ``max_lateral_mm``, ``max_span``) keeps the
        screening and registers the pairs again.
    progress : bool
        tqdm progress bars.
    regularizer, alpha, register_kwargs
        Passed to :func:`femreg.register`; a ``roi`` (x0, x1, y0, y1) mm or ``depth`` (d0, d1) mm among them cuts
        the whole loop to that rectangle before the screening (``region``), as :func:`femreg.register` cuts a
        pair; ``roi="auto"`` (default): RF frames on their echo rectangle (:func:`femreg.echo.find_echo` on the
        first two frames that differ), envelope frames with fill on their fan (``data_mask``); where neither cuts
        anything, the loop is cut above the rows at depth where those two frames do not match after register's
        default start (noise a time-gain compensation lifts to the echo's level:
        :func:`femreg.registration.noise_at_depth`); ``roi=None``: the whole frames.
    on_pair : callable(row), optional
        Called after each registered pair.  One with a true ``reports_progress`` attribute prints its own line
        per pair: off a terminal the registration's progress lines are then left out (one line per pair).
    workers : int
        Local Dask worker processes (:func:`femreg.batch.engine.open_client`, one thread each) for the screening
        and the registrations; 1: all in this process.  With more, the chosen pairs are registered in
        ``workers`` contiguous runs at once, each warm-started within itself: the first pair of each run starts
        from the pyramid, so its field may differ from a one-process run within the registration's tolerance.
    client : distributed.Client, optional
        Use this client's workers instead (its cluster stays up: no start-up cost per loop).
    data_mask : None | (n_axial, n_lateral) bool array
        Where the frames hold data (True): the fan of a scan-converted convex / phased loop.  None (default):
        envelope / B-mode frames with fill (:func:`femreg.echo.find_fill`, from the first and last frames) are
        taken on their fan; RF frames whole.  The loop is cut to the fan's bounding box, screened on the windows
        that see no fill, registered with the fill weighted 0 in eq:IR (``data_mask`` of
        :func:`femreg.register`), and the elastogram is NaN outside the fan.
    geometry : femreg.Convex | femreg.Sector, optional
        Frames (n_samples, n_rays) of a convex or phased array, ``spacing`` the range step dr mm (or (dr, angle
        pitch deg)), ``origin`` (first range mm, 0) (:mod:`femreg.geometry`).  The loop is screened in sample
        space (range, rho_c theta), where a frame is a linear image; every pair is registered by
        :func:`femreg.geometry.register_beam` on one physical mesh (the sample-space mesh mapped), so each strain
        image is the physical axial strain e_xx; they are combined on the samples, and the results are
        scan-converted onto a Cartesian grid (:attr:`ElastogramResult.geometry`).  A ``depth`` (d0, d1) is a
        range along the rays; a rectangle ``roi`` is not supported (no ``data_mask`` either).

    Returns
    -------
    ElastogramResult (``n_usable == 0``: nothing usable; ``exx`` is then all NaN)

    Raises
    ------
    InputError
        Bad frames (fewer than 3, shapes differ, NaN, constant / all-zero, saturated) or parameters.
    """
    t_all = time.perf_counter()
    timings = {}
    if alpha is not None and not _positive_number(alpha):
        # one weight for every pair: a rule ("auto") would pick another weight per pair, so the strain images of
        # the loop would not be comparable
        raise InputError(pass_as(f"elastogram alpha must be None (the default weight) or a positive number, got "
                                 f"{alpha!r}: alpha='auto' is not supported here (choose it on one pair with "
                                 "femreg.register(..., alpha='auto') and pass its .alpha)",
                                 f"elastogram --alpha must be a positive number, got {alpha!r}: one weight for every "
                                 "pair (choose it on one pair with femreg register LOOP --pair I J --alpha auto and "
                                 "pass the alpha it prints)"))
    seq = _validate(frames)
    repeats = repeated_frames(seq)      # frames written twice: said in the result, nothing to register
    if len(repeats) == len(seq) - 1:
        raise InputError(f"all {len(seq)} frames hold the same samples: nothing moved, no strain to image (an "
                         "elastogram needs a loop whose frames differ)")
    beam = _beam(geometry, data_mask, register_kwargs.get("roi", "auto"))
    if beam is not None:            # sample space: the frames as linear images (femreg.geometry)
        from .geometry import beam_spacing, sample_space

        dr, r0 = beam_spacing(spacing, beam, origin)
        spacing, origin = sample_space(beam, np.shape(seq[0]), dr, r0)[1:]
    spacing, origin = validate_spacing(spacing, origin)
    if register_kwargs.pop("check_orientation", True):     # once, before any work, not in every pair's register
        orientation.check(np.asarray(seq[0], dtype=float), spacing)
    region, excluded, mask, digest = None, None, None, None
    first, last = (np.asarray(seq[k], dtype=float) for k in (0, len(seq) - 1))
    roi, depth = register_kwargs.get("roi", "auto"), register_kwargs.get("depth")
    given = depth is not None or (roi is not None and not isinstance(roi, str))
    if beam is not None:
        crop = None
        if depth is not None:       # a range window over every ray: rows only, the rays stay centred on 0
            crop = crop_for(first, last, spacing, origin, roi=None, depth=depth, margin=register_kwargs.get("margin"))
        elif roi is not None and rf_like(first):
            # RF: the ranges with echo, as register and track find them (femreg.echo.find_echo on the first two
            # frames that differ); below the noise floor the strain would be drawn as if it were data.  Rows only:
            # the rays stay centred on 0 (a dead ray is registered as before)
            skip = set(repeats)
            second = next((k for k in range(1, len(seq)) if k not in skip), 1)
            crop = crop_for(first, np.asarray(seq[second], dtype=float), spacing, origin, roi="auto",
                            margin=register_kwargs.get("margin"), fan=True)
            if crop is not None and not crop.region.row_cuts:
                crop = None
        if crop is not None:
            from .geometry import beam_excluded

            (a, b) = (crop.slices[0].start, crop.slices[0].stop)
            n_rays = np.shape(seq[0])[1]
            rho_c = sample_space(beam, np.shape(seq[0]), dr, r0)[0]
            seq = seq[:, a:b] if isinstance(seq, np.ndarray) else [np.asarray(f)[a:b] for f in seq]
            region, excluded = ((a, b), (0, n_rays)), beam_excluded(crop.region, rho_c, rows_only=True)
            r0 = r0 + a * dr
            spacing, origin = validate_spacing(*sample_space(beam, np.shape(seq[0]), dr, r0)[1:])
    elif given:
        # a user's rectangle or depth range: the loop is cut to it (widened by the mesh margin) as register and
        # track cut a pair; every pair is then registered on that crop's mesh
        crop = crop_for(first, last, spacing, origin, roi=roi, depth=depth, margin=register_kwargs.get("margin"),
                        data_mask=data_mask)
        seq, region, origin, excluded = _cut(seq, crop)
    elif roi is not None and data_mask is None and rf_like(first) and find_rf_fan(first, last, spacing,
                                                                                  origin) is None:
        # RF: the echo rectangle register and track detect (femreg.echo.find_echo on the first two frames that
        # differ); below the noise floor the strain would be drawn as if it were data
        skip = set(repeats)
        second = next((k for k in range(1, len(seq)) if k not in skip), 1)
        crop = crop_for(first, np.asarray(seq[second], dtype=float), spacing, origin, roi="auto",
                        margin=register_kwargs.get("margin"), fan=True)
        if crop is not None:
            seq, region, origin, excluded = _cut(seq, crop)
    elif data_mask is not None or roi is not None:
        # the fan whole: its wedges are fixed on the screen, so they are screened and registered with weight 0
        # (femreg.echo.fan_region); RF frames are registered whole unless scan-converted, zero around a fan
        crop = crop_for(first, last, spacing, origin, roi="auto", margin=register_kwargs.get("margin"), fan=True,
                        data_mask=data_mask)
        if data_mask is not None:
            digest = hashlib.sha1(np.packbits(np.asarray(data_mask, bool)).tobytes()
                                  + repr(np.shape(data_mask)).encode()).hexdigest()
        if crop is not None:
            seq, region, origin, excluded = _cut(seq, crop)
            mask = crop.mask
    if region is None and beam is None and roi is not None and not given and data_mask is None:
        # nothing cut by level or fill: noise a time-gain compensation lifts to the echo's level at depth, where
        # the first two frames that differ do not match (femreg.echo.unmatched_crop), as register cuts a pair
        from .registration import noise_at_depth

        second = next((k for k in range(1, len(seq)) if k not in set(repeats)), 1)
        crop = noise_at_depth(first, np.asarray(seq[second], dtype=float), spacing=spacing, origin=origin,
                              regularizer=regularizer, alpha=alpha, **register_kwargs)
        if crop is not None:
            seq, region, origin, excluded = _cut(seq, crop)
    lo, hi = _band(band)
    centre = float(np.sqrt(lo * hi))
    if not (0.0 <= float(persistence) < 1.0):
        raise InputError(pass_as(f"persistence must be in [0, 1), got {persistence!r}",
                                 f"--persistence must be at least 0 and below 1, got {persistence!r}"))
    if isinstance(max_span, bool) or int(max_span) != max_span or max_span < 1:
        raise InputError(pass_as(f"max_span must be an integer >= 1, got {max_span!r}",
                                 f"--max-span must be an integer >= 1, got {max_span!r}"))
    if not (np.isfinite(min_ncc) and -1.0 <= min_ncc <= 1.0):
        raise InputError(f"min_ncc must be in [-1, 1], got {min_ncc!r}")
    n_workers = _check_workers(workers, client)
    n = len(seq)
    shape = np.shape(seq[0])
    extent = np.asarray(shape) * spacing
    max_lat = 0.1 * extent[1] if max_lateral_mm is None else float(max_lateral_mm)
    if not max_lat > 0:
        raise InputError(pass_as(f"max_lateral_mm must be > 0, got {max_lateral_mm!r}",
                                 f"--max-lateral must be > 0 mm, got {max_lateral_mm!r}"))
    reg_name = regularizer if isinstance(regularizer, str) else getattr(regularizer, "name", "custom")

    def frame(k):
        return np.asarray(seq[k], dtype=float)

    params = dict(n_frames=n, shape=[int(s) for s in shape], spacing=[float(s) for s in spacing],
                  origin=[float(s) for s in origin], band=[lo, hi], min_ncc=float(min_ncc), max_lateral_mm=max_lat,
                  max_span=int(max_span), regularizer=str(reg_name), alpha=None if alpha is None else float(alpha),
                  register_kwargs=json.loads(json.dumps(register_kwargs, sort_keys=True, default=repr)))
    if digest is not None:          # a resume with another mask is refused
        params["data_mask"] = digest
    if beam is not None:            # nor one with another probe
        params["geometry"] = beam.to_dict()
    register_kwargs["check_orientation"] = False           # checked above
    if given:                                              # cut above: the pairs' mesh defines the region
        register_kwargs.update(roi=None, depth=None)
    reselected = []
    # the screen does not depend on how pairs are chosen from it: a resume with another band keeps the screen and
    # registers the newly chosen pairs afresh (their warm starts follow the band)
    out = open_run_folder(output_dir, params, resume=resume, record="elastogram.json", started=("screen.npz",),
                          kind="an elastogram run", reselect=("band", "min_ncc", "max_lateral_mm", "max_span"),
                          on_reselect=reselected.extend)
    if reselected and out is not None:
        for f in (out / "pairs").glob("pair_*.npz"):
            f.unlink()
    if out is not None:
        (out / "pairs").mkdir(exist_ok=True)

    with _pool(n_workers, client, seq) as (client, fpath):
        # -- 1. screening ----------------------------------------------------------------------------------------------
        t = time.perf_counter()
        scr = _Screener(frame(0), spacing, origin, regularizer if isinstance(regularizer, str) else "momentum-stress",
                        mask)
        # the strain images are combined on every qa-th row (about 3 per speckle cell: elements span several cells)
        qa = scr.q
        cshape = (len(range(0, shape[0], qa)), shape[1])
        cspacing = np.array([qa * spacing[0], spacing[1]])
        sfile = None if out is None else out / "screen.npz"
        if resume and sfile is not None and sfile.exists():
            with np.load(sfile, allow_pickle=False) as z:
                e_c, lat_c, ncc_c, coef_c = (np.array(z[k]) for k in ("strain", "lateral_mm", "ncc", "coef"))
        elif client is not None:
            # contiguous runs of pairs, two tasks per worker (the envelopes of a run are computed once, as here)
            futs = [client.submit(_screen_task, scr, fpath, k0, k1, pure=False)
                    for k0, k1 in _chunks(n - 1, 2 * n_workers)]
            parts = client.gather(futs)
            coef_c, e_c, lat_c, ncc_c = (np.concatenate([p[m] for p in parts]) for m in range(4))
        else:
            b = progress_bar(progress, n - 1, "screen", "pair")
            parts = []
            try:
                for k0, k1 in _chunks(n - 1, 1 if b is None else n - 1):
                    parts.append(_screen_run(scr, frame, k0, k1))
                    if b is not None:
                        b.update(1)
            finally:
                if b is not None:
                    b.close()
            coef_c, e_c, lat_c, ncc_c = (np.concatenate([p[m] for p in parts]) for m in range(4))
            if sfile is not None:
                atomic_savez(sfile, strain=e_c, lateral_mm=lat_c, ncc=ncc_c, coef=coef_c)
        timings["screen"] = time.perf_counter() - t

        # -- 2. choose -------------------------------------------------------------------------------------------------
        t = time.perf_counter()
        rows = screen_pairs(e_c, lat_c, ncc_c, band=(lo, hi), max_span=max_span, min_ncc=min_ncc,
                            max_lateral_mm=max_lat, repeated=repeats)
        for r in rows:
            r.update(registered=False, usable=False, message="")
        # pairs over more than one frame step: screened directly (envelopes of i and j)
        far = [(r["ref"], r["mov"]) for r in rows if r["selected"] and r["mov"] > r["ref"] + 1]
        if client is not None and len(far) > 1:
            futs = [client.submit(_direct_task, scr, fpath, far[a0:a1], pure=False)
                    for a0, a1 in _chunks(len(far), n_workers)]
            matched = dict(zip(far, [m for part in client.gather(futs) for m in part]))
        else:
            matched = {(i, j): scr.match(scr.env(i, frame(i)), scr.env(j, frame(j))) for i, j in far}
        direct = {}
        for r in rows:
            if not r["selected"]:
                continue
            i, j = r["ref"], r["mov"]
            if j == i + 1:
                coef = coef_c[i]
            else:
                coef, e, lat, c = matched[(i, j)]
                r.update(strain=e, lateral_mm=lat, ncc=min(r["ncc"], c))
                if c < min_ncc or not lo <= abs(e) <= hi or abs(lat) > max_lat:
                    r["selected"] = False
                    r["message"] = (f"direct screening: strain {100 * e:.2f} %, NCC {c:.2f}, lateral {lat:.2f} mm")
                    continue
            direct[(i, j)] = coef
        timings["choose"] = time.perf_counter() - t

        # -- 3. register -----------------------------------------------------------------------------------------------
        t = time.perf_counter()
        chosen = [r for r in rows if r["selected"]]
        mesh = register_kwargs.pop("mesh", None)
        if mesh is None and register_kwargs.get("element_size") is None and \
                register_kwargs.get("strategy", "auto") == "auto":
            es = tuple(default_settings(shape, spacing, scr.stats, **element_rule(reg_name)).element_size)
            mesh = roi_mesh(shape, spacing, origin, element_size=es, margin=register_kwargs.pop("margin", None))
        elif mesh is None:
            check_element_size(register_kwargs.get("element_size"), spacing)
            mesh = roi_mesh(shape, spacing, origin, element_size=register_kwargs.pop("element_size", None),
                            margin=register_kwargs.pop("margin", None))
        lattice = None
        if beam is not None:
            # one physical mesh: the sample-space one mapped; register_beam maps its nodes back for its
            # sample-space stage (femreg.geometry)
            from .geometry import physical_mesh

            rho_c = float(beam.radius_mm + r0 + 0.5 * (shape[0] - 1) * dr)
            lattice = (mesh, beam, rho_c)
            mesh = physical_mesh(mesh, beam, rho_c)
            reg_args = dict(spacing=dr, origin=(r0, 0.0), geometry=beam, regularizer=regularizer, alpha=alpha,
                            **register_kwargs)
        else:
            reg_args = dict(spacing=spacing, origin=origin, regularizer=regularizer, alpha=alpha, data_mask=mask,
                            **register_kwargs)
        todo = [(r["ref"], r["mov"], r["strain"], direct[(r["ref"], r["mov"])]) for r in chosen]
        by_key = {(r["ref"], r["mov"]): r for r in chosen}
        # off a terminal an on_pair that writes a line per pair is the progress: no bar's lines as well
        b = progress_bar(progress, len(chosen), "register", "pair", on_pair)

        def done(i, j, rec):
            r = by_key[(i, j)]
            r["registered"] = True
            r["usable"], r["message"] = _verdict(rec, lo, hi)
            if r["usable"]:
                r["strain"] = rec["mean_strain"]
            if on_pair is not None:
                on_pair(r)
            if b is not None:
                b.set_postfix_str(f"{i}->{j} {100 * rec['mean_strain']:+.2f} %" + ("" if r["usable"] else " rejected"))
                b.update(1)

        try:
            if client is not None and len(todo) > 1:
                # contiguous runs of pairs, one task per worker: each run warm-starts within itself (its first pair
                # starts from the pyramid)
                futs = []
                for a0, a1 in _chunks(len(todo), n_workers):
                    part = todo[a0:a1]
                    # the first run's first pair is the cut decision's (when it is the pair that decision searched):
                    # its search goes with it, as one process shares it (femreg.registration.sharing_start)
                    futs.append(client.submit(_register_task, fpath, part, mesh, qa, (lo, hi), out, resume, reg_args,
                                              lattice, shared_search() if a0 == 0 else None, pure=False))
                per_pair = {}
                for got in client.gather(futs):
                    per_pair.update(got)
                for i, j, _, _ in todo:
                    done(i, j, per_pair[(i, j)])
            else:
                per_pair = _register_run(frame, todo, mesh, qa, (lo, hi), out, resume, reg_args, on_rec=done,
                                         lattice=lattice)
        finally:
            if b is not None:
                b.close()
        timings["register"] = time.perf_counter() - t

    # -- 4. normalise and combine ------------------------------------------------------------------------------
    t = time.perf_counter()
    cum = np.zeros((n, 3, 2))        # screened affine motion frame 0 -> frame k (summed: small strain)
    cum[1:] = np.cumsum(coef_c, axis=0)
    cine, cine_frames = [], []
    D = W = None
    prev_pair = None
    best_mean, best, qual, ref_frame = -1.0, np.full(cshape, np.nan), np.zeros(cshape), 0
    inside = np.ones(shape, bool) if mask is None else mask.inside
    cin = inside[::qa]                # the fan on the combined rows: persistence moves weight across its edge
    for r in rows:
        if not r["usable"]:
            continue
        rec = per_pair[(r["ref"], r["mov"])]
        exx = rec["exx"]
        ok = np.isfinite(exx)
        s = np.where(ok, exx / np.mean(exx[ok]), 0.0)
        w = np.where(ok, _weight(rec["quality"], rec["mean_strain"] / centre), 0.0)
        if D is not None and persistence > 0:
            # previous reference -> its moving frame by the registered field, then on by the screened motion
            i0, j0 = prev_pair
            p_rec = per_pair[prev_pair]
            field = (p_rec["ux"], p_rec["uy"])
            if beam is not None:        # the physical field as the motion of the samples (sample space)
                from .geometry import to_sample_displacement

                field = to_sample_displacement(*field, beam, cspacing[0], r0, cspacing[1])
            WD, Wm = _move([W * D, W], cum[r["ref"]] - cum[j0], cspacing, origin, field=field)
            # only onto the mesh's pixels: moved laterally (fat sliding 0.02 mm a frame) the edge column took a
            # sliver of weight from its neighbour, 1e-4 of the median, drawn black on the quality picture
            WD, Wm = np.where(ok, WD, 0.0), np.where(ok, Wm, 0.0)
            W = w + persistence * Wm
            D = np.where(W > 0, (w * s + persistence * WD) / np.where(W > 0, W, 1.0), 0.0)
        else:
            D, W = s, w
        prev_pair = (r["ref"], r["mov"])
        cine.append(np.where((W > 0) & cin, D, np.nan).astype(np.float32))
        cine_frames.append(int(r["ref"]))
        if W.mean() > best_mean:
            best_mean, best, qual, ref_frame = float(W.mean()), D.copy(), W.copy(), int(r["ref"])
    best, qual = _to_pixel_rows(best, qual, shape, qa)
    qual = np.where(inside, qual, 0.0)
    best = np.where(qual > 0, best, np.nan)
    cine = np.array(cine, dtype=np.float32).reshape((-1,) + cshape)
    data_mask = None if mask is None else mask.inside.copy()
    beam_kw = {}
    if beam is not None:            # results in physical x, y: scan-converted, NaN outside the fan
        from .geometry import frame_grid, to_cartesian

        grid = frame_grid(beam, shape, dr, r0)
        cgrid = _row_grid(grid, qa)
        best = to_cartesian(best, beam, dr, r0, grid)
        fan = np.isfinite(to_cartesian(np.ones(shape), beam, dr, r0, grid))
        # uncovered samples NaN, not 0: interpolated towards 0 the fan's edge read as pixels of no weight
        qual = np.where(qual > 0, qual, np.nan)
        qual = np.where(fan, np.nan_to_num(to_cartesian(qual, beam, dr, r0, grid), nan=0.0), 0.0)
        best = np.where(qual > 0, best, np.nan)
        cine = to_cartesian(cine, beam, cspacing[0], r0, cgrid).astype(np.float32).reshape((-1,) + tuple(cgrid[0]))
        spacing, origin, cspacing, data_mask = np.asarray(grid[1]), np.asarray(grid[2]), np.asarray(cgrid[1]), fan
        beam_kw = dict(geometry=beam, sample_spacing=(dr, float(beam.angle_pitch_deg)), sample_origin=(r0, 0.0))
    timings["combine"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_all
    return ElastogramResult(exx=best, quality=qual, ref_frame=int(ref_frame), spacing=spacing, origin=origin,
                            cine=cine, cine_spacing=cspacing,
                            cine_frames=cine_frames, pairs=rows,
                            screen=dict(strain=e_c, lateral_mm=lat_c, ncc=ncc_c), timings=timings, region=region,
                            excluded=excluded, data_mask=data_mask, repeated=repeats, **beam_kw)


def write_pairs_csv(path, rows) -> None:
    """``pairs.csv``: one row per candidate pair, columns :data:`PAIR_COLUMNS` (selected = registered and
    usable)."""
    atomic_write_text(path, _row_csv(rows))
