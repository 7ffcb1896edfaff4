"""Images on a pixel grid: validation, normalisation, cubic B-spline interpolation, reference gradient.

Convention: an image is a 2D array indexed ``[i, j]`` = (axial x, lateral y); pixel ``[i, j]`` has its centre at
``origin + (i * dx, j * dy)`` (mm).

Normalisation (why alpha is scale-free)
---------------------------------------
The image term psi of eq:IR is quadratic in the intensities, so multiplying both RF frames by a gain ``c``
multiplies psi by ``c**2`` and would change the meaning of every regularisation weight alpha.  femreg therefore
subtracts each image's mean and divides it by its standard deviation, e.g. ``s = sqrt(mean((I_1 - m_1)**2))`` for
the reference.  RF is zero-mean already (the subtraction changes it by round-off, or removes a scanner's DC
offset); envelope and B-mode frames are not: a display B-mode (8-bit grey levels, mean ~200, speckle std ~20)
divided by its RMS kept its speckle at 0.1 of unit scale, psi 100 x weaker against alpha, and the default alpha
flattened a 2.5 mm stiff inclusion of a scan-converted L12 loop into uniform strain (9.6 % strain error, the
same as a uniform field's; 5.0 % with alpha 0.001).  The mean also sets what "zero outside the image" reads: the
image's average level, not black.  After that the reference has unit variance, psi is measured in mm^2 and an
alpha means the same thing for any amplitude scale or offset.  :func:`normalize_pair` returns the scale.

A gain change between the frames (the user turned the gain, or one frame is stored as integer counts) would
leave the moving image ``g`` times brighter than the reference: psi then holds ``(g - 1)**2 I**2``, which no motion
explains, and the data term's weight against alpha changes by ``g``.  So the moving image is divided by its *own*
RMS (per-frame normalisation).  Measured (R_P_sigma, total strain error, a 1 % compression pair with a stiff
inclusion, paper probe): with the reference's RMS for both, gains 0.9 / 0.95 / 1.1 gave 10.2 / 8.8 / 7.7 % against
7.6 % at matched gain; per frame, 7.586 % for every gain from 0.3 to 3 and for int16 counts.  On frames of matched
gain it moves results by round-off-sized amounts: robustness cases within 0.016 points (comp 1-8 %, inclusions,
10-frame sequence), in vivo frames 1 -> 6 NCC after 0.8124 -> 0.8108 (seq299, RMS ratio 1.11) and 0.8970 ->
0.8968 (seq304).

Interpolation
-------------
``I(x)`` between pixel centres is the cubic B-spline interpolant (Unser 1999, doi:10.1109/79.799930; scipy.ndimage
conventions): the spline coefficients are computed once (``spline_filter``, mirror boundary) and every
evaluation sums the 4 x 4 coefficient stencil around the point (:func:`cubic_at_index`); points outside the
image (outside the pixel cells, i.e. more than half a pixel beyond the first/last pixel centre) read 0, as in
the paper.  The reference gradient of eq:wfnew is the exact
gradient of the same interpolant; at pixel centres (spline knots) it is a closed-form stencil of the
coefficients, :meth:`SplineImage.gradient_at_pixels`.

Speed: the re-interpolation of I_2 at every pixel is the inner loop of Gauss-Newton.  When numba is installed,
:func:`cubic_at_index` evaluates the 4 x 4 tensor B-spline stencil in a compiled loop (:mod:`femreg._kernels`),
otherwise ``map_coordinates`` does; the two agree to round-off (~1e-12 of the image amplitude).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from .errors import InputError, counted, pass_as

from . import _kernels

__all__ = ["validate_image", "repeated_frames", "leading_repeats", "repeats_listed", "repeat_note", "refuse_repeated_start", "validate_samples", "validate_spacing", "normalize_pair", "SplineImage", "pixel_axes", "cubic_at_index", "ncc"]

#: A frame with more than this fraction of its samples at its largest magnitude is clipped (saturated).
SATURATED_FRACTION = 0.5

#: Pole of the cubic B-spline prefilter, sqrt(3) - 2 (the constant of scipy's ni_splines.c).
_CUBIC_POLE = -0.267949192431122706472553658494127633


def cubic_at_index(padded, idx, shape, out=None):
    """Cubic B-spline interpolant at fractional pixel indices ``idx`` (2, n), 0 outside the pixel cells.

    ``padded`` are the spline coefficients of an image of ``shape`` mirror-extended by 2 on every side
    (:attr:`SplineImage._padded`).  Compiled loop with numba, ``scipy.ndimage.map_coordinates`` without.
    """
    idx = np.asarray(idx, dtype=float)
    hi0, hi1 = float(shape[0]) - 0.5, float(shape[1]) - 0.5
    if out is None:
        out = np.empty(idx.shape[1])
    if _kernels.use_compiled():
        return _kernels.cubic_kernel(padded, np.ascontiguousarray(idx[0]), np.ascontiguousarray(idx[1]), hi0, hi1, out)
    v = ndimage.map_coordinates(padded, idx + 2.0, order=3, mode="constant", cval=0.0, prefilter=False,
                                output=out)
    outside = ~((idx[0] >= -0.5) & (idx[0] <= hi0) & (idx[1] >= -0.5) & (idx[1] <= hi1))
    if outside.any():
        v[outside] = 0.0
    return v


def require_spacing(spacing) -> None:
    """Raise :class:`InputError` saying what ``spacing`` is when it was not given (None)."""
    if spacing is None:
        raise InputError("spacing is required: (dx, dy) mm, the axial sample spacing (c / (2 fs): 0.0193 mm at "
                         "40 MHz and 1540 m/s) and the lateral line pitch, e.g. spacing=(0.02, 0.2); a volume "
                         "takes (dx, dy, dz)")


def validate_spacing(spacing, origin=(0.0, 0.0), *, n: int = 2):
    """Return ``(spacing, origin)`` as float arrays of shape (n,) mm, ``n`` = 2 (dx, dy) or 3 (dx, dy, dz),
    raising :class:`InputError` if invalid.  One number is the spacing of every axis; for a volume the 2D
    default origin (0, 0) means (0, 0, 0)."""
    try:
        sp = np.asarray(spacing, dtype=float).reshape(-1)
        org = np.asarray(origin, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InputError(f"spacing/origin must be numbers: {exc}") from None
    if sp.size == 1:
        sp = np.repeat(sp, n)
    if sp.size != n:
        raise InputError(f"spacing must be (dx, dy) in mm, got {spacing!r}" if n == 2 else
                         f"a volume needs spacing (dx, dy, dz) in mm, got {spacing!r}")
    if not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise InputError(f"spacing must be finite and > 0 mm, got ({', '.join(f'{v:g}' for v in sp)})")
    if n == 3 and org.size == 2 and np.all(org == 0):       # the 2D default origin
        org = np.zeros(3)
    if org.size != n or not np.all(np.isfinite(org)):
        raise InputError(f"origin must be two finite numbers (mm), got {origin!r}" if n == 2 else
                         f"a volume needs origin (x0, y0, z0) as three finite numbers (mm), got {origin!r}")
    return sp, org


def repeated_frames(frames) -> list:
    """Indices k >= 1 of the frames whose samples equal frame k - 1's exactly (a scanner or an export that wrote
    one frame twice): nothing moved between them, so there is nothing to register.  ``frames``: a sequence of
    arrays of one shape."""
    return [k for k in range(1, len(frames)) if np.array_equal(frames[k], frames[k - 1])]


def leading_repeats(repeats) -> int:
    """The last frame of the run of frames that repeat frame 0 (:func:`repeated_frames`' ``repeats``): 0 when frame
    1 differs from it."""
    rep, last = set(repeats), 0
    while last + 1 in rep:
        last += 1
    return last


def repeats_listed(repeats, limit: int = 10) -> str:
    """The repeated frames as "k = k - 1" pairs, the first ``limit`` of them (", ..." after)."""
    rep = list(repeats)
    return ", ".join(f"{k} = {k - 1}" for k in rep[:limit]) + (", ..." if len(rep) > limit else "")


def repeat_note(k: int) -> str:
    """The message a tracking run gives frame ``k`` when it repeats frame ``k - 1`` (not registered)."""
    return f"frame {k} repeats frame {k - 1} (identical samples): not registered, its field kept"


def refuse_repeated_start(repeats, n_frames: int, what: str = "tracking") -> None:
    """InputError when every frame repeats frame 0 (nothing moved), or when frame 1 does: the first pair sets
    the mesh and the region registered, so the run starts at the last frame of the leading repeats instead (the
    message names it, counted from 0)."""
    last = leading_repeats(repeats)
    if n_frames >= 2 and last >= n_frames - 1:
        raise InputError(f"all {n_frames} frames hold the same samples: nothing moved, nothing to register "
                         f"({what} needs frames that differ)")
    if last:
        raise InputError(f"frames 0-{last} hold the same samples (the recording repeats frame 0): the first pair "
                         f"sets the mesh and the region registered, so {what} cannot start on a repeat; start at "
                         f"frame {last} ("
                         + pass_as(f"frames=slice({last}, None); CLI: --frames {last}:", f"--frames {last}:")
                         + ")")


def validate_image(image, name: str = "image") -> np.ndarray:
    """Check a 2D finite, non-constant real image; return it as float64.  Raises :class:`InputError`."""
    return validate_samples(image, name, ndim=2)


def validate_samples(image, name: str = "image", *, ndim: int = 2) -> np.ndarray:
    """Check a real, finite, non-constant, unsaturated array of ``ndim`` = 2 (axial, lateral) or 3 (axial,
    lateral, elevational) axes, at least 4 samples along each; return it as float64, else :class:`InputError`
    naming the problem."""
    if np.iscomplexobj(image):
        raise InputError(f"{name} is complex: pass the real RF (or the envelope |IQ|), not IQ data")
    try:
        a = np.asarray(image, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} is not a numeric array: {exc}") from None
    if a.ndim != ndim:
        if ndim == 2:
            raise InputError(f"{name} must be 2D (axial, lateral), or for femreg.register / track a volume "
                             f"(axial, lateral, elevational) with 3 spacing values; got ndim={a.ndim} "
                             f"shape={a.shape}")
        raise InputError(f"{name} must be 3D (axial, lateral, elevational), got ndim={a.ndim} shape={a.shape}")
    unit = "pixel" if ndim == 2 else "voxel"
    if min(a.shape) < 4:
        raise InputError(f"{name} is too small: shape {a.shape}, need at least "
                         + ("4 x 4 pixels" if ndim == 2 else "4 voxels along every axis"))
    bad = ~np.isfinite(a)
    if bad.any():
        first = ", ".join(str(int(i)) for i in np.argwhere(bad)[0])
        raise InputError(f"{name} has NaN/Inf at {counted(int(bad.sum()), unit)} (first at [{first}]): every "
                         f"sample must be finite; crop the frames to where they hold data or set those samples")
    if np.ptp(a) == 0:
        raise InputError(f"{name} is constant (value {a.flat[0]:g}): nothing to register"
                         + (" (all zero: an empty or blanked frame)" if a.flat[0] == 0 else ""))
    top = np.abs(a).max()
    clipped = np.count_nonzero(np.abs(a) == top) / a.size
    if clipped > SATURATED_FRACTION:
        raise InputError(f"{name} is saturated: {clipped:.0%} of its samples sit at the clip level {top:g} "
                         f"(lower the gain or store unclipped RF)")
    return a


def pixel_axes(shape, spacing, origin):
    """Pixel-centre coordinates along each axis: ``(x (n_axial,), y (n_lateral,))`` in mm."""
    return (origin[0] + spacing[0] * np.arange(shape[0]), origin[1] + spacing[1] * np.arange(shape[1]))


#: Fall (dB) of the reference's echo level along its straight-line trend over the registered depth above which
#: :func:`depth_fall_note` says so.  Robustness and study pairs (no attenuation) span 0.9-6.1 dB row to row; a
#: 15 MHz musculoskeletal pair without TGC falls 27 dB over 24 mm, the in vivo sequences 15-21 dB over 37 mm.
LEVEL_FALL_DB = 10.0
#: Depth (mm) over which a row's mean square is averaged before the trend is fitted.
LEVEL_SMOOTH_MM = 2.0


def depth_trend_db(reference, spacing) -> np.ndarray:
    """The straight-line trend with depth of the reference's echo level, (n_axial,) dB: ``10 log10`` of each row's
    mean square averaged over :data:`LEVEL_SMOOTH_MM`, fitted by least squares against depth.  A line, not the
    profile itself: the exponential fall attenuation gives (what a scanner's time-gain compensation undoes), not
    the layers' own echogenicity."""
    from scipy.ndimage import uniform_filter1d

    img = np.asarray(reference, float)
    ms = np.mean(np.square(img - np.mean(img)), axis=1)
    n = max(1, int(round(LEVEL_SMOOTH_MM / float(np.ravel(spacing)[0]))))
    ms = uniform_filter1d(ms, n, mode="nearest")
    db = 10.0 * np.log10(np.maximum(ms, np.max(ms) * 1e-12))
    x = np.arange(img.shape[0], dtype=float)
    slope, icpt = np.polyfit(x, db, 1)
    return icpt + slope * x


def depth_fall_note(reference, spacing) -> list:
    """``[note]`` where the reference's echo weakens by more than :data:`LEVEL_FALL_DB` along its depth trend
    (:func:`depth_trend_db`; a recording without time-gain compensation), else ``[]``.  eq:objf weighs one alpha
    against the image term of the average echo (:func:`normalize_pair`), so where the echo is weak the same alpha
    regularises many times more: a 15 MHz pair falling 27 dB flattened a stiff nodule 12.6 dB under the average
    (strain ratio 1.01 against 2.14; 1.49 with the frames levelled first).  Levelling inside register was measured
    and not adopted (docs/robustness.md, "An echo that falls with depth"): the note says it instead."""
    if np.asarray(reference).shape[0] < 2:
        return []
    trend = depth_trend_db(reference, spacing)
    fall = float(trend[0] - trend[-1])
    if not fall > LEVEL_FALL_DB:
        return []
    return [f"the echo weakens {fall:.0f} dB with depth (no time-gain compensation?): one alpha regularises the deep, "
            f"weak echo more than the shallow, which can flatten deep lesions; a scanner's TGC applied to the frames "
            f"first evens that out"]


def normalize_pair(reference, moving, mask=None):
    """Each image minus its mean, over its standard deviation (see module docstring); ``mask`` (bool, the
    images' shape): both taken over its True pixels only (the fan of a scan-converted frame, not its fill).
    Returns ``(ref, mov, scale)``, ``scale`` the reference's standard deviation."""
    out = []
    for img, what in ((reference, "reference"), (moving, "moving")):
        img = np.asarray(img, float)
        sel = img if mask is None else img[mask]
        m = float(np.mean(sel))
        s = float(np.sqrt(np.mean(np.square(sel - m))))
        if not s > 0:
            raise InputError(f"{what} image is constant: nothing to register")
        out.append(((img - m) / s, s))
    return out[0][0], out[1][0], out[0][1]


class SplineImage:
    """Cubic B-spline interpolant of an image on its pixel grid, zero outside.

    Parameters
    ----------
    data : (n_axial, n_lateral) array
    spacing, origin : (2,) mm
    """

    def __init__(self, data, spacing, origin=(0.0, 0.0)):
        self.data = np.ascontiguousarray(data, dtype=float)
        self.spacing = np.asarray(spacing, dtype=float)
        self.origin = np.asarray(origin, dtype=float)
        self.shape = self.data.shape
        #: bool (shape), False where eq:IR leaves the reference pixel out (fill of a fan), or None
        self.weights_mask = None
        # Prefilter once; every later evaluation uses prefilter=False.
        # Mirror-extend the coefficients by 2 (as scipy does internally) so that points within half a pixel of
        # the edge interpolate instead of dropping to zero through round-off; zero outside is applied
        # explicitly at the pixel-cell boundary [-1/2, n - 1/2].
        if _kernels.use_compiled() and min(self.shape) >= 3:    # the same numbers, faster
            self._padded = _kernels.spline_coefficients(self.data, _CUBIC_POLE)
            self.coeffs = self._padded[2:-2, 2:-2]
        else:
            self.coeffs = ndimage.spline_filter(self.data, order=3, mode="mirror")
            self._padded = np.pad(self.coeffs, 2, mode="reflect")
        self._hi = np.array(self.shape, dtype=float) - 0.5

    def to_index(self, points):
        """(n, 2) mm -> (2, n) fractional pixel indices."""
        pts = np.asarray(points, dtype=float)
        return ((pts - self.origin) / self.spacing).T

    def __call__(self, points, out=None):
        """Interpolated values at ``points`` (n, 2) mm; 0 outside the image."""
        return self.at_index(self.to_index(points), out=out)

    def at_index(self, idx, out=None):
        """Values at fractional pixel indices ``idx`` (2, n)."""
        return cubic_at_index(self._padded, idx, self.shape, out=out)

    def gradient(self, points, h: float = 1e-3):
        """Gradient (n, 2) [dI/dx, dI/dy] per mm of the interpolant at arbitrary points.

        Central difference of the spline with step ``h`` pixels; inside a cell the spline is cubic, so the
        error is exactly ``h**2/6 * I'''`` (about 1e-7 relative for h = 1e-3).
        """
        idx = self.to_index(points)
        g = np.empty((idx.shape[1], 2))
        for a in range(2):
            e = np.zeros((2, 1))
            e[a] = h
            g[:, a] = (self.at_index(idx + e) - self.at_index(idx - e)) / (2 * h * self.spacing[a])
        return g

    def gradient_at_pixels(self, block=None):
        """Exact gradient of the interpolant at every pixel centre: ``(gx, gy)``, each (n_axial, n_lateral);
        with ``block`` = (row slice, column slice) (unit steps) at the pixels of that block only.

        At a knot the cubic B-spline has weights (1/6, 4/6, 1/6) and derivative weights (-1/2, 0, 1/2), so
        dI/dx[i, j] = ((S_y c)[i+1, j] - (S_y c)[i-1, j]) / (2 dx) with S_y the lateral (1, 4, 1)/6 smoother,
        and the coefficients mirror-extended exactly as scipy evaluates them.
        """
        if block is None:
            c = np.pad(self.coeffs, 1, mode="reflect")
        else:   # the coefficients mirror-extended by 1 around the block: a view of the 2-padded ones
            (r0, r1, _), (c0, c1, _) = (b.indices(n) for b, n in zip(block, self.shape))
            if _kernels.use_compiled() and self._padded.dtype == np.float64:
                nr, nc = max(r1 - r0, 0), max(c1 - c0, 0)
                gx, gy = np.empty(nr * nc), np.empty(nr * nc)
                _kernels.knot_gradient(self._padded, r0, nr, c0, nc, 2.0 * self.spacing[0], 2.0 * self.spacing[1],
                                       gx, gy)
                return gx.reshape(nr, nc), gy.reshape(nr, nc)
            c = self._padded[r0 + 1:r1 + 3, c0 + 1:c1 + 3]
        sx = (c[:-2, :] + 4.0 * c[1:-1, :] + c[2:, :]) / 6.0   # smooth along axis 0
        sy = (c[:, :-2] + 4.0 * c[:, 1:-1] + c[:, 2:]) / 6.0   # smooth along axis 1
        gx = (sy[2:, :] - sy[:-2, :]) / (2.0 * self.spacing[0])
        gy = (sx[:, 2:] - sx[:, :-2]) / (2.0 * self.spacing[1])
        return gx, gy


def ncc(a, b) -> float:
    """Normalised cross-correlation of two equally shaped sample arrays (zero-mean, unit-norm)."""
    a = np.asarray(a, float).ravel() - np.mean(a)
    b = np.asarray(b, float).ravel() - np.mean(b)
    d = np.linalg.norm(a) * np.linalg.norm(b)
    return float(a @ b / d) if d > 0 else 0.0
