"""Coarse-to-fine initial guess of the default ``strategy="auto"`` of :func:`femreg.register`, with defaults
measured from the images.

Gauss-Newton on an RF image is a local method: it converges to the correlation peak within about a quarter of
the RF period of its start, and from further away to a neighbouring peak one period off ("peak hopping").  The
paper's NCC block matching (fixed 5 x 9 mm windows, +-1.5 mm search) gives such a start only inside its protocol.
Here the start comes from a pyramid, as in optical flow (Lucas-Kanade pyramids), elastix and GLUE:

1. :func:`speckle_statistics` -- RF period and speckle cell size (axial, lateral) from the spectrum and the
   envelope autocorrelation; :func:`default_settings` derives element size, decimation, windows and search
   ranges from them and from the image extent (instead of the paper's millimetres).
2. Top level, envelopes low-passed and decimated to ~3 samples per speckle cell (axially; laterally per pulse
   cell, see :func:`default_settings`): a global search over translations up to 10 % of the image depth (axial)
   and width (lateral), axial strains from -12 % to +6 % and, when these leave the match poor, in-plane
   rotations up to 6 degrees (:func:`global_search`), then NCC block matching of speckle-sized windows on the
   envelope of the moving image warped by that field, searching only around it (:func:`local_search`), again
   around the affine fit of the windows that matched while that fit moves the field (:func:`refine_affine`).
3. Gauss-Newton on the envelopes with a mesh twice as coarse as the final one, from that field (the envelope has
   no carrier, so its basin is a speckle cell wide, not a quarter period).
4. The final level (RF, fine mesh) is solved by :func:`femreg.register` from the envelope-level field; the
   envelope-level field is also the reference the repair stage (:mod:`femreg.repair`) checks the RF result
   against.

Every level warps the moving image by the whole field of the level above (not only its affine part).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from . import _kernels
from .blockmatch import block_match
from .data_term import SSDTerm
from .image import SplineImage
from .mesh import roi_mesh
from .pixels import PixelQuadrature, PointLocator
from .scaling import effective_alpha
from .solver import Objective, gauss_newton
from .speckle import (SpeckleStats, envelope, rf_period, speckle_cell,  # noqa: F401  (also femreg.pyramid.*)
                      speckle_statistics)

__all__ = ["SpeckleStats", "PyramidSettings", "speckle_statistics", "rf_period", "default_settings", "envelope",
           "global_search", "local_search", "field_at", "pyramid_initial_guess", "PyramidGuess",
           "pyramid_search", "pyramid_solve", "PyramidSearch", "MAX_ELEMENT_SIZE", "element_rule", "refine_affine",
           "gaussian_decimate", "image_settings", "STRUCTURE_RATIO"]

#: Largest motion the top level searches, as a fraction of the image extent (axial, lateral).
SEARCH_FRACTION = (0.10, 0.10)
#: Largest default element size (mm) of the momentum regularisers.  Strain features users look for are a few mm
#: (the edge of a 5-10 mm inclusion); the mesh alone misses a 10 mm inclusion's axial strain by 9-10 % at 2 mm
#: elements and 6-7 % at 1-1.5 mm.  Measured on the robustness benchmark (R_P_sigma defaults, total strain error)
#: with the cap at 1.5 mm instead of the speckle rule's 2.1 mm (5.5 MHz) / 3.3 mm (3 MHz) / 1.6 mm (7.5 MHz):
#: every inclusion case lower or equal (3 MHz stiff plane stress 12.9 -> 9.4, 5.5 MHz stiff plane stress 4 %
#: 11.3 -> 10.1, stiff plane strain 1 % 14.3 -> 13.6, soft plane strain 4 % 12.9 -> 12.1), uniform compression
#: 0.1-1.1 -> 0.1-0.7, bending 4.4 -> 5.8 (the one loss); 1.2 mm lowered the inclusions further but bending to
#: 7.8.  The strain regularisers got worse on finer meshes (R_eps, 8 % compression at 3 MHz 18.5 -> 37.6 %, R_eps_i
#: stiff plane stress at 3 MHz 30.8 -> 44.3 %: their best alpha does not follow the 1 / area scaling of
#: :mod:`femreg.scaling` below 2 mm) and keep the speckle rule.
MAX_ELEMENT_SIZE = 1.5
#: Axial speckle cells per element of the speckle rule (:func:`default_settings`): 6, and 4 for R_P_sigma.  With 4
#: (R_P_sigma, robustness benchmark): 12 MHz soft plane stress 10.5 -> 9.5 %, 7.5 MHz soft plane stress 11.4 ->
#: 9.7, 15 MHz soft plane strain 13.0 -> 12.4, other cases equal; in vivo frames 1 -> 6 (elements 1.44 / 1.2 ->
#: 0.96 / 0.8 mm) NCC after 0.808 / 0.891 -> 0.813 / 0.897 and row alternation of e_xx 1.18 / 0.88 -> 0.59 / 0.55
#: (seq299 / seq304).  R_P_eps lost with 4 (12 MHz soft plane stress 19.3 -> 22.9 %), R_eps on most cases.
AXIAL_CELLS_PER_ELEMENT = {"momentum-stress": 4.0}
DEFAULT_AXIAL_CELLS = 6.0


def element_rule(regularizer) -> dict:
    """The element-size keywords of :func:`default_settings` for ``regularizer``: ``axial_cells`` per element and
    the largest size ``max_size`` (mm, or None): R_P_sigma 4 and 1.5, R_P_eps 6 and 1.5, other regularisers 6 and
    None.  See :data:`MAX_ELEMENT_SIZE`."""
    name = regularizer if isinstance(regularizer, str) else ""
    return {"axial_cells": AXIAL_CELLS_PER_ELEMENT.get(name, DEFAULT_AXIAL_CELLS),
            "max_size": MAX_ELEMENT_SIZE if name.startswith("momentum") else None}
#: Axial strains tried by the global search (fraction; negative = compression).
GLOBAL_STRAINS = tuple(np.round(np.arange(-0.12, 0.0601, 0.01), 3))
#: In-plane rotations (degrees) the global search also tries when shift and axial strain leave its NCC below
#: :data:`ROTATION_SCAN_NCC`.
GLOBAL_ROTATIONS_DEG = (-6.0, -5.0, -4.0, -3.0, -2.0, -1.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
ROTATION_SCAN_NCC = 0.5


#: Below this fraction of the envelope's cell (per axis) the speckle's own cell sizes the block matching
#: (:func:`default_settings`): uniform speckle reads 0.9-1.0 (one sample of quantisation), echo structure 0.1-0.7.
STRUCTURE_RATIO = 0.75


@dataclass
class PyramidSettings:
    """Defaults derived from the image: ``element_size`` (2,) mm of the final mesh, ``decimation`` (axial factor
    of the envelope level), ``window`` / ``search`` (2,) mm of the local block matching."""

    element_size: np.ndarray
    decimation: int
    window: np.ndarray
    search: np.ndarray
    lateral_decimation: int = 1


def default_settings(shape, spacing, stats: SpeckleStats, element_size=None, max_size=None,
                     axial_cells: float = DEFAULT_AXIAL_CELLS, speckle=None) -> PyramidSettings:
    """Defaults from the image (all mm).

    * Element size: square, ``max(axial_cells axial cells, 1.1 lateral cells)`` -- with 6 cells about 2 mm for the
      paper's probe (cell 0.35 x 1.8 mm), 3.3 mm at 3 MHz, 0.9 mm at 12 MHz -- at most ``max_size`` (mm) and 1/12
      of the smaller image extent, at least 2 lines and 8 samples; register passes :func:`element_rule` of its
      regulariser (R_P_sigma: 4 cells, at most 1.5 mm).  The cell here is the smaller of the envelope's and the pulse's
      (:class:`SpeckleStats`): on tissue the envelope cell measures the echo structure, and elements sized from
      it (capped at 2.13 mm on the 40 x 25.6 mm in vivo frames) are too coarse for the motion of that
      structure: in vivo frames 1 -> 6 (R_P_sigma) the solve then fits each node row to its own layer and e_xx
      alternates from one element row to the next (mean ``|second difference across rows|`` / mean ``|e_xx|`` 2.0 on
      seq299, 1.8 on seq304, the same from any seed and at 3x the iterations), with a lower NCC after.  The
      pulse cell gives 1.4 / 1.2 mm there; on simulated speckle both cells agree and nothing changes.
      Decimation, windows and search ranges keep the envelope cell (the envelope level matches envelopes).
    * Envelope decimation: ~3 samples per axial speckle cell; laterally ~3 samples per lateral pulse cell (the
      smaller of the two cells: on tissue the envelope's lateral cell is the echo structure's, 2.4-3.2 mm on the
      in vivo frames, and decimating by it (4-5 lines) moved the seq299 frames 1 -> 6 result (NCC after 0.813 ->
      0.804, mean e_xx -1.13 -> -0.93 %); by the pulse cell they keep every line, simulated speckle every other).
    * Local block matching: windows of 8 x 3 cells (at least 1/12 x 1/8 of the image), search 3 x 2 cells.
    * ``speckle``: the speckle's own cell ((2,) mm, :func:`femreg.speckle.speckle_cell`, the envelope over its
      local RMS), or None.  Per axis where it reads under :data:`STRUCTURE_RATIO` of the envelope cell (the
      envelope cell then holds echo structure: layers, a brightness falling with depth), decimation, windows and
      search are sized from it; the element size is not (sized from it too, the 12.5 MHz pair 2 -> 3 of
      benchmarks/hf_lines_first.py read e_xx 9.4 % wrong instead of 7.5 %, and a simulated pair with the echo
      falling 30 dB over 30 mm 0.4-0.7 points more total strain error).  On a layered echogenicity (6 dB RMS
      in 2 x 10 mm patches) the envelope cell reads 1.1-1.2 x 4.2 mm for 0.42-0.46 x 1.8-2.4 mm: its windows
      and search failed the pair (total strain error 111-115 %), these give 9.5 %.  Uniform speckle reads the
      same cell both ways, within a sample or two (ratio 0.9-1), and keeps its settings.
    """
    spacing = np.asarray(spacing, float)
    extent = np.asarray(shape, float) * spacing
    if element_size is None:
        cell = stats.cell if stats.pulse_cell is None else np.minimum(stats.cell, stats.pulse_cell)
        h = max(float(axial_cells) * cell[0], 1.1 * cell[1])
        h = min(h, extent.min() / 12.0, np.inf if max_size is None else float(max_size))
        h = np.maximum(np.array([h, h]), np.array([8 * spacing[0], 2 * spacing[1]]))
    else:
        h = np.broadcast_to(np.asarray(element_size, float), (2,)).copy()
    if speckle is not None:
        own = np.asarray(speckle, float)
        stats = replace(stats, cell=np.where(np.isfinite(own) & (own < STRUCTURE_RATIO * stats.cell), own,
                                             stats.cell))
    q = int(max(1, np.floor(stats.cell[0] / (3.0 * spacing[0]))))
    lat = stats.cell[1] if stats.pulse_cell is None else min(stats.cell[1], stats.pulse_cell[1])
    ql = int(max(1, np.floor(lat / (3.0 * spacing[1]))))
    window = np.maximum([8.0 * stats.cell[0], 3.0 * stats.cell[1]], extent / np.array([12.0, 8.0]))
    window = np.minimum(window, extent / 2.0)
    search = np.array([3.0 * stats.cell[0], 2.0 * stats.cell[1]])
    return PyramidSettings(element_size=h, decimation=q, window=window, search=search, lateral_decimation=ql)


def image_settings(image, spacing, element_size=None, regularizer=None):
    """``(stats, settings)`` of ``image`` ((n_axial, n_lateral), spacing mm): its :func:`speckle_statistics` and
    :func:`default_settings` (:func:`element_rule` of ``regularizer``), the block matching sized from the speckle's
    own cell (:func:`femreg.speckle.speckle_cell`, ``speckle=`` of :func:`default_settings`)."""
    stats = speckle_statistics(image, spacing)
    own = speckle_cell(image, spacing, stats=stats)
    return stats, default_settings(np.shape(image), spacing, stats, element_size, speckle=own,
                                   **element_rule(regularizer))


def gaussian_decimate(e, q: int, axis: int):
    """``scipy.ndimage.gaussian_filter1d(e, q / 2, axis)`` (truncated at 4 sigma, "reflect" boundary) at every
    q-th sample only; compiled, the filter's own weights and boundary (equal to round-off), q times less work."""
    if not _kernels.use_compiled():
        return ndimage.gaussian_filter1d(e, 0.5 * q, axis=axis)[(slice(None),) * axis + (slice(None, None, q),)]
    sigma = 0.5 * q
    r = int(4.0 * sigma + 0.5)
    x = np.arange(-r, r + 1)
    w = np.exp(-0.5 / (sigma * sigma) * x ** 2)
    w = w / w.sum()
    n = e.shape[axis]
    taps = np.arange(0, n, q)[:, None] + x[None, :]
    taps = np.mod(taps, 2 * n)                          # "reflect": d c b a | a b c d | d c b a, period 2n
    taps = np.where(taps >= n, 2 * n - 1 - taps, taps)
    return _kernels.decimating_filter(np.ascontiguousarray(e), w, taps.astype(np.int64), axis)


def _decimated_envelopes(ref, mov, q, ref_envelope=None, ql: int = 1):
    """Low-passed (Gaussian, sigma q/2 samples axially, ql/2 laterally) and decimated envelopes (by q axially,
    ql laterally), zero mean, unit RMS (ref)."""
    out = []
    for img, env in ((ref, ref_envelope), (mov, None)):
        e = envelope(img) if env is None else env
        if ql > 1:
            e = gaussian_decimate(e, ql, 1)
        if q > 1:
            e = gaussian_decimate(e, q, 0)
        out.append(e)
    m = out[0].mean()
    s = out[0].std() or 1.0
    return (out[0] - m) / s, (out[1] - m) / s


def _warp(image, spacing, origin, field_grid):
    """image(x + u(x)) on its own pixel grid, u given per pixel (n_a, n_l, 2) mm; cubic, zero outside.

    ``scipy.ndimage.map_coordinates(image, .., order=3, mode="constant")``: the cubic B-spline of the mirror-
    extended image, 0 where a point lies outside [0, n - 1] on either axis; with numba the same interpolant from
    :class:`femreg.image.SplineImage`'s compiled prefilter and evaluation (equal to round-off, faster)."""
    ii, jj = np.meshgrid(np.arange(image.shape[0]), np.arange(image.shape[1]), indexing="ij")
    idx = [ii + field_grid[..., 0] / spacing[0], jj + field_grid[..., 1] / spacing[1]]
    if not (_kernels.use_compiled() and min(image.shape) >= 3):
        return ndimage.map_coordinates(image, idx, order=3, mode="constant", cval=0.0)
    img = SplineImage(image, spacing, origin)
    flat = np.stack([idx[0].ravel(), idx[1].ravel()])
    out = img.at_index(flat)
    out[(flat[0] < 0) | (flat[0] > image.shape[0] - 1) | (flat[1] < 0) | (flat[1] > image.shape[1] - 1)] = 0.0
    return out.reshape(image.shape)


def _pixel_points(shape, spacing, origin):
    x = origin[0] + spacing[0] * np.arange(shape[0])
    y = origin[1] + spacing[1] * np.arange(shape[1])
    X, Y = np.meshgrid(x, y, indexing="ij")
    return np.column_stack([X.ravel(), Y.ravel()])


def _axial_resample(image, pos) -> np.ndarray:
    """``image`` sampled at fractional row positions ``pos`` (n_rows_out,), the same for every column: cubic
    convolution (Keys, a = -0.5; 4 taps, no prefilter), zero outside.  Used for the axial-strain pre-warps of
    the global search, where a full 2D spline warp per trial strain dominated its cost."""
    img = np.asarray(image, float)
    if _kernels.use_compiled():
        return _kernels.axial_resample(np.ascontiguousarray(img), np.asarray(pos, float),
                                       np.empty((np.size(pos), img.shape[1])))
    n = img.shape[0]
    i0 = np.floor(pos).astype(np.int64)
    t = pos - i0
    # Keys kernel weights for taps i0-1 .. i0+2
    w = np.stack([((-0.5 * t + 1.0) * t - 0.5) * t,
                  (1.5 * t - 2.5) * t * t + 1.0,
                  ((-1.5 * t + 2.0) * t + 0.5) * t,
                  (0.5 * t - 0.5) * t * t])
    out = np.zeros((pos.size, img.shape[1]))
    for k in range(4):
        idx = i0 - 1 + k
        wk = np.where((idx >= 0) & (idx < n), w[k], 0.0)
        out += wk[:, None] * img[np.clip(idx, 0, n - 1)]
    return out


def _peak_offset(cm, c0, cp) -> float:
    """Sub-sample offset of a parabola through three samples around a maximum (0 if not concave)."""
    den = cm - 2.0 * c0 + cp
    return float(np.clip(0.5 * (cm - cp) / den, -0.5, 0.5)) if (np.isfinite(den) and den < 0) else 0.0


def global_search(ref_env, mov_env, spacing, origin, *, strains=GLOBAL_STRAINS, fraction=SEARCH_FRACTION,
                  rotations=GLOBAL_ROTATIONS_DEG, rotation_below: float = ROTATION_SCAN_NCC):
    """Best (shift, axial strain, in-plane rotation) over translations up to ``fraction`` of the extent, the
    given axial strains and, when that leaves the NCC below ``rotation_below``, the given rotations (degrees).

    For each strain e the moving envelope is pre-warped by u_x = e (x - x_mid); the central part of the reference
    (the image less ``fraction`` of its extent on every side) is matched by NCC over every shift, by one FFT
    correlation (the template's transform is computed once) and box sums of the moving image for the norms.
    The peak is refined by a parabola per axis.  A rotation turns the axial displacement across the width (3
    degrees: +-0.8 mm over 30 mm) and decorrelates the large template (global NCC 0.08-0.22 at 2-5 degrees,
    0.36-0.99 for compression up to 10 %, bending and shear without it), so only then the moving envelope is
    also pre-rotated about the image centre by each angle of ``rotations``, scanned over every other strain, and
    the best strain refined on the full strain list at the best angle.  Returns ``(coef, ncc)``: the affine
    field coefficients (3, 2) as in :meth:`BlockMatchResult.affine_fit` and the peak NCC."""
    from scipy import fft as sfft

    spacing = np.asarray(spacing, float)
    origin = np.asarray(origin, float)
    ref = np.asarray(ref_env, float)
    mov = np.asarray(mov_env, float)
    n = np.array(ref.shape)
    s = np.minimum(np.ceil(np.asarray(fraction) * n - 1e-9).astype(int), (n - 2) // 2)
    s = np.maximum(s, 0)
    w = n - 2 * s                                      # template: the reference less s on every side
    T = ref[s[0]:s[0] + w[0], s[1]:s[1] + w[1]]
    T = T - T.mean()
    tn = float(np.sqrt(np.sum(T * T)))
    shape = (sfft.next_fast_len(int(n[0]), real=True), sfft.next_fast_len(int(n[1]), real=True))
    FT = np.conj(sfft.rfft2(T, s=shape))
    xm = origin[0] + 0.5 * (n[0] - 1) * spacing[0]
    centre = origin + 0.5 * (n - 1) * spacing
    x = origin[0] + spacing[0] * np.arange(n[0])
    na, nl = 2 * s[0] + 1, 2 * s[1] + 1
    fct = 1.0 / (shape[0] * shape[1])                 # irfft2's normalisation, applied after its last pass

    def scan(image, strain_list, Q):
        best = (None, -np.inf, 0.0)
        for e in strain_list:
            R = _axial_resample(image, np.arange(n[0]) + e * (x - xm) / spacing[0]) if e else image
            # C[d] = sum T * R[d:d+w]: irfft2 as its two passes (the same values), the second on the na rows of
            # lags only
            X = sfft.rfft2(R, s=shape)
            X *= FT
            C = sfft.irfft(sfft.ifft(X, axis=0, norm="forward")[:na], n=shape[1], norm="forward")[:, :nl] * fct
            if _kernels.use_compiled():
                S1, S2 = _kernels.box_sums(np.ascontiguousarray(R), int(w[0]), int(w[1]), int(na), int(nl))
            else:
                I1 = np.zeros((n[0] + 1, n[1] + 1))
                I2 = np.zeros((n[0] + 1, n[1] + 1))
                I1[1:, 1:] = R.cumsum(0).cumsum(1)
                I2[1:, 1:] = (R * R).cumsum(0).cumsum(1)

                def box(I):
                    return (I[w[0]:w[0] + na, w[1]:w[1] + nl] - I[:na, w[1]:w[1] + nl] - I[w[0]:w[0] + na, :nl]
                            + I[:na, :nl])
                S1, S2 = box(I1), box(I2)
            var = np.maximum(S2 - S1 * S1 / (w[0] * w[1]), 0.0)
            den = tn * np.sqrt(var)
            ncc = np.where(den > 1e-12 * max(float(den.max()), 1e-300), C / np.where(den > 0, den, 1.0), -np.inf)
            k = np.unravel_index(int(np.argmax(ncc)), ncc.shape)
            c = float(ncc[k])
            if c > best[1]:
                d = np.array(k, float)
                if 0 < k[0] < na - 1:
                    d[0] += _peak_offset(ncc[k[0] - 1, k[1]], c, ncc[k[0] + 1, k[1]])
                if 0 < k[1] < nl - 1:
                    d[1] += _peak_offset(ncc[k[0], k[1] - 1], c, ncc[k[0], k[1] + 1])
                sh = (d - s) * spacing
                # reference(x) ~ image(z), z = A x + b with A = diag(1 + e, 1) (the strain pre-warp and shift),
                # image(z) = moving(c + Q (z - c)) (the rotation pre-warp): u(x) = (Q A - I) x + Q (b - c) + c
                A = np.diag([1.0 + e, 1.0])
                b = np.array([sh[0] * (1.0 + e) - e * xm, sh[1]])
                M = Q @ A - np.eye(2)
                coef = np.zeros((3, 2))
                coef[0] = Q @ (b - centre) + centre
                coef[1] = M[:, 0]
                coef[2] = M[:, 1]
                best = (coef, c, e)
        return best

    coef, c, _ = scan(mov, strains, np.eye(2))
    if c < rotation_below and len(rotations):
        pts = _pixel_points(mov.shape, spacing, origin)
        found = None
        for deg in rotations:
            th = np.deg2rad(float(deg))
            Q = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
            rot = _warp(mov, spacing, origin, ((pts - centre) @ Q.T + centre - pts).reshape(mov.shape + (2,)))
            cand = scan(rot, strains[::2], Q)
            if cand[1] > c:
                coef, c, found = cand[0], cand[1], (rot, Q, cand[2])
        if found is not None:                   # the full strain list near the best strain, at the best angle
            rot, Q, e0 = found
            near = [e for e in strains if abs(e - e0) < 1.5 * _strain_step(strains)]
            cand = scan(rot, near, Q)
            if cand[1] > c:
                coef, c = cand[0], cand[1]
    return coef, c


def _strain_step(strains) -> float:
    d = np.diff(np.sort(np.asarray(strains, float)))
    d = d[d > 0]
    return float(d.min()) if d.size else 0.0


def _affine(coef, pts):
    return np.column_stack([coef[0, c] + coef[1, c] * pts[:, 0] + coef[2, c] * pts[:, 1] for c in range(2)])


def local_search(ref_env, mov_env, spacing, origin, prior, settings: PyramidSettings):
    """Block matching of ``ref_env`` against ``mov_env`` warped by ``prior`` (callable points -> (n, 2) mm),
    searching ``settings.search`` around it; returns callable total field (prior + filtered residual)."""
    spacing = np.asarray(spacing, float)
    pts = _pixel_points(ref_env.shape, spacing, origin)
    grid = prior(pts).reshape(ref_env.shape + (2,))
    warped = _warp(mov_env, spacing, origin, grid)
    bm = block_match(ref_env, warped, spacing, origin, window=tuple(settings.window), overlap=(0.5, 0.5),
                     search=tuple(settings.search), median_size=3, subsample=True, compand_strain=None)

    def total(p):
        return prior(p) + bm(p)
    return total, bm


#: Windows whose peak NCC reaches this enter the affine refit of :func:`refine_affine`.
AFFINE_FIT_NCC = 0.5
#: A refit affine field is searched around again when it moves some image corner by more than this fraction
#: of the local search range (either component).
AFFINE_REFIT_SHIFT = 0.5
#: Most local-search passes around refit affine fields after the first.
AFFINE_PASSES = 3


def refine_affine(bm, prior_coef, *, min_ncc: float = AFFINE_FIT_NCC):
    """Full affine fit (3, 2) of the total block-matching field ``prior + bm`` over the windows whose peak NCC
    reaches ``min_ncc``; ``None`` when they do not determine one (:meth:`BlockMatchResult.affine_fit`).  The
    prior is affine, so the fit of the sum is the prior plus the fit of ``bm``.

    The global search models a shift and an axial strain only: an in-plane rotation or a simple shear makes the
    axial displacement vary across the width (3 degrees: +-0.8 mm at the edges of a 30 mm image), beyond the
    local search range at the edges, while the windows near the centre still match.  Their affine fit carries
    the rotation out to the edges for the next pass."""
    coef = bm.affine_fit(min_ncc)
    return None if coef is None else np.asarray(prior_coef, float) + coef


def field_at(mesh, u, points, locator: PointLocator | None = None) -> np.ndarray:
    """Nodal field ``u`` (2 n_nodes,) of ``mesh`` at ``points`` (n, 2) mm -> (n, 2) mm; points outside the
    mesh take the value at the nearest point of the mesh's bounding box (exact for the structured ROI meshes)."""
    pts = np.asarray(points, float).reshape(-1, 2)
    lo, hi = mesh.p.min(axis=1), mesh.p.max(axis=1)
    q = np.clip(pts, lo, hi)
    loc = (locator or PointLocator(mesh)).locate(q)
    out = np.zeros((len(q), 2))
    out[loc.inside, 0] = np.sum(loc.N * u[0::2][loc.nodes], axis=1)
    out[loc.inside, 1] = np.sum(loc.N * u[1::2][loc.nodes], axis=1)
    if not loc.inside.all():             # clamped points on a non-convex user mesh: nearest node
        from scipy.spatial import cKDTree

        _, k = cKDTree(mesh.p.T).query(q[~loc.inside])
        out[~loc.inside] = np.column_stack([u[0::2][k], u[1::2][k]])
    return out


@dataclass
class PyramidGuess:
    """Output of :func:`pyramid_initial_guess`: the envelope-level field on its coarse mesh (``mesh``, ``u``),
    the speckle statistics and settings, the global search's NCC and the block matching of the top level."""

    mesh: object
    u: np.ndarray
    stats: SpeckleStats
    settings: PyramidSettings
    global_ncc: float
    blockmatch: object
    timings: dict

    def __call__(self, points) -> np.ndarray:
        return field_at(self.mesh, self.u, points)


@dataclass
class PyramidSearch:
    """Output of :func:`pyramid_search` (steps 2 and the search of 3): the decimated envelopes ``er``, ``em`` on
    the spacing ``sp_c`` mm from ``origin`` mm, the global search's NCC, the local search's field and its block
    matching (:class:`femreg.blockmatch.BlockMatchResult`, read by :func:`femreg.echo.unmatched_crop` before any
    solve), seconds per sub-stage."""

    er: np.ndarray
    em: np.ndarray
    sp_c: np.ndarray
    origin: np.ndarray
    global_ncc: float
    field: object
    blockmatch: object
    stats: SpeckleStats
    settings: PyramidSettings
    timings: dict


def pyramid_search(ref, mov, spacing, origin, *, stats: SpeckleStats, settings: PyramidSettings,
                   ref_envelope=None) -> PyramidSearch:
    """The envelopes, global search and local search of :func:`pyramid_initial_guess` on normalised RF images
    ``ref``, ``mov`` (n_a, n_l), spacing and origin mm: everything before the coarse Gauss-Newton solve (which
    :func:`pyramid_solve` adds).  ``ref_envelope``: :func:`envelope` of ``ref`` if already computed."""
    import time

    timings = {}
    spacing = np.asarray(spacing, float)
    origin = np.asarray(origin, float)
    t = time.perf_counter()
    q = settings.decimation
    ql = settings.lateral_decimation
    er, em = _decimated_envelopes(ref, mov, q, ref_envelope, ql)
    sp_c = np.array([q * spacing[0], ql * spacing[1]])
    timings["envelopes"] = time.perf_counter() - t

    t = time.perf_counter()
    coef, gncc = global_search(er, em, sp_c, origin)
    timings["global_search"] = time.perf_counter() - t

    t = time.perf_counter()
    field, bm = local_search(er, em, sp_c, origin, lambda p: _affine(coef, p), settings)
    # rotation / shear beyond the search range at the edges: search again around the affine fit of the windows
    # that matched, while it moves the field and raises the mean window NCC (normal pairs: no second pass)
    corners = np.array([[origin[0] + a * sp_c[0] * (er.shape[0] - 1), origin[1] + b * sp_c[1] * (er.shape[1] - 1)]
                        for a in (0, 1) for b in (0, 1)])
    for _ in range(AFFINE_PASSES):
        new = refine_affine(bm, coef)
        if new is None:
            break
        shift = np.abs(_affine(new, corners) - _affine(coef, corners)).max(axis=0)
        if not np.any(shift > AFFINE_REFIT_SHIFT * np.asarray(settings.search)):
            break
        field2, bm2 = local_search(er, em, sp_c, origin, lambda p, c=new: _affine(c, p), settings)
        if not float(np.mean(bm2.ncc)) > float(np.mean(bm.ncc)):
            break
        coef, field, bm = new, field2, bm2
    timings["local_search"] = time.perf_counter() - t
    return PyramidSearch(er, em, sp_c, origin, gncc, field, bm, stats, settings, timings)


def pyramid_solve(search: PyramidSearch, *, regularizer_factory, margin=None, maxiter: int = 20, tol: float = 1e-3,
                  linear_solver: str = "splu") -> PyramidGuess:
    """Step 3's Gauss-Newton on the envelopes of ``search`` (:func:`pyramid_search`), on a mesh of twice the
    final element size, from the local search's field; kept only where it lowers the envelopes' SSD."""
    import time

    er, em, sp_c, origin, settings, field = (search.er, search.em, search.sp_c, search.origin, search.settings,
                                             search.field)
    timings = dict(search.timings)
    t = time.perf_counter()
    mesh = roi_mesh(er.shape, sp_c, origin, element_size=tuple(2.0 * settings.element_size), margin=margin)
    quad = PixelQuadrature(mesh, er.shape, sp_c, origin)
    data = SSDTerm(quad, SplineImage(er, sp_c, origin), SplineImage(em, sp_c, origin))
    reg = regularizer_factory()
    reg.alpha = effective_alpha(reg.alpha, mesh)
    reg.setup(mesh)
    pts = mesh.p.T
    v = field(pts)
    u0 = np.empty(2 * len(pts))
    u0[0::2], u0[1::2] = v[:, 0], v[:, 1]
    psi0 = data.energy(u0)          # before the solve: its first evaluation then comes from the cache
    gn = gauss_newton(Objective(data, reg), u0, maxiter=maxiter, tol=tol, linear_solver=linear_solver)
    u = gn.x if data.energy(gn.x) <= psi0 else u0
    timings["envelope_gauss_newton"] = time.perf_counter() - t
    return PyramidGuess(mesh=mesh, u=u, stats=search.stats, settings=settings, global_ncc=search.global_ncc,
                        blockmatch=search.blockmatch, timings=timings)


def pyramid_initial_guess(ref, mov, spacing, origin, *, regularizer_factory, alpha, stats: SpeckleStats,
                          settings: PyramidSettings, margin=None, maxiter: int = 20, tol: float = 1e-3,
                          linear_solver: str = "splu", ref_envelope=None) -> PyramidGuess:
    """Steps 2-3 of the module docstring on normalised RF images ``ref``, ``mov`` (n_a, n_l):
    :func:`pyramid_search`, then :func:`pyramid_solve`.

    ``regularizer_factory()`` returns a fresh regulariser (user alpha set); its weight on the coarse mesh is
    scaled by :func:`femreg.scaling.effective_alpha`.  ``ref_envelope``: :func:`envelope` of ``ref`` if already
    computed (e.g. ``stats.envelope`` when the statistics come from ``ref`` itself)."""
    search = pyramid_search(ref, mov, spacing, origin, stats=stats, settings=settings, ref_envelope=ref_envelope)
    return pyramid_solve(search, regularizer_factory=regularizer_factory, margin=margin, maxiter=maxiter, tol=tol,
                         linear_solver=linear_solver)
