"""What users would otherwise pick to measure motion and strain in RF pairs, written as a user would.

Every method takes ``(ref, mov, spacing, origin)`` (arrays (n_axial, n_lateral), mm) with the registration
convention ``ref(x) ~ mov(x + u(x))`` and returns a dict of (n_axial, n_lateral) float arrays on the reference pixel
grid: ``ux, uy`` (mm) and ``exx, eyy, exy`` (small strain, ``exy = (dux/dy + duy/dx) / 2``), NaN where the method
gives nothing.

* :func:`ncc_block_match`: NCC block matching, a coarse envelope pass with a wide search
  (``skimage.feature.match_template``) guiding a fine RF pass (box-filtered NCC over a small search), 3-point
  parabolic sub-sample peak fit, 3 x 3 median filter, least-squares strain (linear fit over a few windows).
  The standard time-delay estimator of strain elastography: Ophir et al., Ultrason. Imaging 13 (1991),
  doi:10.1177/016173469101300201; sub-sample fit and least-squares strain: Kallel & Ophir, Ultrason. Imaging 19
  (1997), doi:10.1177/016173469701900303.
* :func:`bspline_sitk`: SimpleITK multi-resolution B-spline registration (LBFGS-B, correlation metric) after an
  affine stage, on smoothed envelopes (Klein et al., elastix, IEEE TMI 29 (2010), doi:10.1109/TMI.2009.2035616;
  SimpleITK: Lowekamp et al., Front. Neuroinform. 7 (2013), doi:10.3389/fninf.2013.00045).
* :func:`optical_flow_skimage`: scikit-image TV-L1 optical flow (Zach, Pock & Bischof, DAGM 2007,
  doi:10.1007/978-3-540-74936-3_22) on envelopes resampled to square pixels, least-squares strain.

SimpleITK and scikit-image are benchmark-only dependencies (``pip install femreg[bench]``).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage, signal
from scipy.interpolate import RegularGridInterpolator

__all__ = ["lsq_strain", "ncc_block_match", "bspline_sitk", "optical_flow_skimage", "envelope"]


def envelope(rf) -> np.ndarray:
    """``|hilbert(rf)|`` along the axial axis (0)."""
    return np.abs(signal.hilbert(np.asarray(rf, float), axis=0))


def _odd(n) -> int:
    n = max(3, int(round(n)))
    return n if n % 2 else n + 1


def lsq_strain(ux, uy, spacing, window) -> dict:
    """Least-squares strain: the slope of a plane fitted to ``u`` over a ``window = (n_ax, n_lat)`` samples box
    (Savitzky-Golay, order 1, along one axis, box mean along the other: the same as the 2D plane fit).
    ``spacing``: sample spacing (mm) of ``ux``/``uy``.  Returns ``exx, eyy, exy``."""
    wa, wl = _odd(window[0]), _odd(window[1])
    dx, dy = float(spacing[0]), float(spacing[1])

    def d(u, axis):
        n = u.shape[axis]
        w, other, h = (wa, wl, dx) if axis == 0 else (wl, wa, dy)
        w = min(w, n if n % 2 else n - 1)
        if w < 3:
            g = np.gradient(u, h, axis=axis) if n > 1 else np.zeros_like(u)
        else:
            g = signal.savgol_filter(u, w, 1, deriv=1, delta=h, axis=axis, mode="interp")
        return ndimage.uniform_filter1d(g, min(other, u.shape[1 - axis]), axis=1 - axis, mode="nearest")

    return dict(exx=d(ux, 0), eyy=d(uy, 1), exy=0.5 * (d(ux, 1) + d(uy, 0)))


def _parabolic(c_m, c_0, c_p):
    den = c_m - 2.0 * c_0 + c_p
    return np.where(den < 0, 0.5 * (c_m - c_p) / np.where(den < 0, den, -1.0), 0.0)


def _match(ref, mov, centres, half, search_a, search_l, seed_px, subsample):
    """NCC peak of the ``(2 half + 1)`` windows of ``ref`` at ``centres`` (k, 2) pixel indices in ``mov`` within
    ``+- search`` pixels of ``centre + seed_px``.  Returns displacement (k, 2) pixels and peak NCC (k,)."""
    from skimage.feature import match_template

    na, nl = ref.shape
    ha, hl = half
    out = np.full((len(centres), 2), np.nan)
    peak = np.zeros(len(centres))
    for k, ((ci, cj), (si, sj)) in enumerate(zip(centres, np.rint(seed_px).astype(int))):
        T = ref[ci - ha:ci + ha + 1, cj - hl:cj + hl + 1]
        a0, a1 = ci - ha + si - search_a, ci + ha + si + search_a + 1
        l0, l1 = cj - hl + sj - search_l, cj + hl + sj + search_l + 1
        a0c, a1c, l0c, l1c = max(a0, 0), min(a1, na), max(l0, 0), min(l1, nl)
        if a1c - a0c < T.shape[0] or l1c - l0c < T.shape[1] or T.std() == 0:
            continue
        c = match_template(mov[a0c:a1c, l0c:l1c], T)
        i, j = np.unravel_index(int(np.argmax(c)), c.shape)
        di = dj = 0.0
        if subsample:
            if 0 < i < c.shape[0] - 1:
                di = float(_parabolic(c[i - 1, j], c[i, j], c[i + 1, j]))
            if 0 < j < c.shape[1] - 1:
                dj = float(_parabolic(c[i, j - 1], c[i, j], c[i, j + 1]))
        out[k] = (a0c + i + di - (ci - ha), l0c + j + dj - (cj - hl))
        peak[k] = c[i, j]
    return out, peak


def _window_grid(n, half, step):
    return np.arange(half, n - half, max(1, int(step)))


def _ncc_shifts(ref, mov, centres, half, search_a, search_l):
    """NCC of the ``(2 half + 1)`` windows of ``ref`` centred at ``centres`` (k, 2) with the same windows of ``mov``
    shifted by every (a, l) in ``[-search_a, search_a] x [-search_l, search_l]`` pixels: box sums of products
    (``scipy.ndimage.uniform_filter``), one pass per shift.  Returns (2 search_a + 1, 2 search_l + 1, k)."""
    size = (2 * half[0] + 1, 2 * half[1] + 1)
    ci, cj = centres[:, 0], centres[:, 1]

    def box(a):
        return ndimage.uniform_filter(a, size, mode="constant")[ci, cj]

    r = ref - box(ref).mean()
    mr, mr2 = box(r), box(r * r)
    out = np.empty((2 * search_a + 1, 2 * search_l + 1, len(ci)))
    for ia, a in enumerate(range(-search_a, search_a + 1)):
        for il, sl in enumerate(range(-search_l, search_l + 1)):
            m = np.roll(mov, (-a, -sl), axis=(0, 1))        # m[i, j] = mov[i + a, j + sl]
            mm, mm2, rm = box(m), box(m * m), box(r * m)
            den = np.sqrt(np.maximum(mr2 - mr**2, 1e-30) * np.maximum(mm2 - mm**2, 1e-30))
            out[ia, il] = (rm - mr * mm) / den
    return out


def _peak(c):
    """Sub-sample peak (axial, lateral offsets from the search centre, pixels) and its NCC, per column of
    ``c`` (na, nl, k): arg max plus a 3-point parabolic fit along each axis."""
    na, nl, k = c.shape
    flat = c.reshape(na * nl, k)
    idx = np.argmax(flat, axis=0)
    ia, il = np.unravel_index(idx, (na, nl))
    kk = np.arange(k)
    pk = c[ia, il, kk]
    da = np.zeros(k)
    dl = np.zeros(k)
    ok = (ia > 0) & (ia < na - 1)
    da[ok] = _parabolic(c[ia[ok] - 1, il[ok], kk[ok]], pk[ok], c[ia[ok] + 1, il[ok], kk[ok]])
    ok = (il > 0) & (il < nl - 1)
    dl[ok] = _parabolic(c[ia[ok], il[ok] - 1, kk[ok]], pk[ok], c[ia[ok], il[ok] + 1, kk[ok]])
    return np.column_stack([ia + da - (na - 1) // 2, il + dl - (nl - 1) // 2]), pk


def ncc_block_match(ref, mov, spacing, origin=(0.0, 0.0), *, window_mm=(2.0, 2.0), step_mm=(0.5, 0.5),
                    coarse_window_mm=(5.0, 4.0), search_fraction=0.12, strain_window_mm=(3.0, 5.0)) -> dict:
    """Two-pass NCC block matching with sub-sample peak fit and least-squares strain.

    Pass 1 (guide): envelope windows ``coarse_window_mm``, half overlap, searched over ``+- search_fraction`` of
    the image depth axially and of its width laterally (motion up to ~10 % of the image), median-filtered 3 x 3.
    Pass 2: the moving RF warped by the guide (cubic), then RF windows ``window_mm`` (at least 3 lines wide) every
    ``step_mm`` searched ``+-0.5 mm`` axially and ``+-1`` line laterally, parabolic peak fit, 3 x 3 median filter.
    Strain: :func:`lsq_strain` over ``strain_window_mm`` (axial, lateral) of window positions.
    """
    ref = np.asarray(ref, float)
    mov = np.asarray(mov, float)
    dx, dy = float(spacing[0]), float(spacing[1])
    na, nl = ref.shape
    # pass 1: envelope (decimated to ~0.05 mm axially), big windows, wide search
    er, k = _decimated_envelope(ref, dx, 0.05)
    em, _ = _decimated_envelope(mov, dx, 0.05)
    ne = er.shape[0]
    ha = max(2, int(round(coarse_window_mm[0] / (k * dx) / 2)))
    hl = max(1, int(round(coarse_window_mm[1] / dy / 2)))
    ha, hl = min(ha, (ne - 1) // 4), min(hl, max(1, (nl - 1) // 4))
    ci, cj = _window_grid(ne, ha, ha), _window_grid(nl, hl, max(1, hl))
    C = np.array([(i, j) for i in ci for j in cj])
    sa = int(round(search_fraction * ne))
    sl = max(1, int(round(search_fraction * nl)))
    d1, pk = _match(er, em, C, (ha, hl), sa, sl, np.zeros((len(C), 2)), subsample=True)
    # outliers: weak peaks or peaks on the (possibly image-clipped) search border -> nearest good window
    top = C[:, 0] - ha + d1[:, 0]                          # first row of the matched window in em
    bad = ~np.all(np.isfinite(d1), axis=1) | (pk < 0.5) | (np.abs(d1[:, 0]) > sa - 1)
    bad |= (top < 0.5) | (top + 2 * ha > ne - 1.5)
    if bad.any() and (~bad).any():
        d1[bad] = d1[~bad][np.argmin(((C[bad, None, :] - C[None, ~bad, :]) ** 2).sum(-1), axis=1)]
    d1 = np.nan_to_num(d1.reshape(len(ci), len(cj), 2))
    d1[..., 0] *= k                                        # decimated -> RF axial pixels
    for c in range(2):
        d1[..., c] = ndimage.median_filter(d1[..., c], size=3, mode="nearest")
    guide = RegularGridInterpolator((ci * k, cj), d1, bounds_error=False, fill_value=None,
                                    method="linear" if min(len(ci), len(cj)) > 1 else "nearest")
    I, J = np.meshgrid(np.arange(na), np.arange(nl), indexing="ij")
    G = guide(np.column_stack([I.ravel(), J.ravel()])).reshape(na, nl, 2)
    warped = ndimage.map_coordinates(mov, [I + G[..., 0], J + G[..., 1]], order=3, mode="constant")
    # pass 2: RF, small windows, +-0.5 mm around the guide
    ha = max(2, int(round(window_mm[0] / dx / 2)))
    hl = max(1, int(round(window_mm[1] / dy / 2)))
    sa2 = max(2, int(round(0.5 / dx)))
    fi = _window_grid(na, ha + sa2, round(step_mm[0] / dx))
    fj = _window_grid(nl, hl + 1, max(1, round(step_mm[1] / dy)))
    F = np.array([(i, j) for i in fi for j in fj])
    d2, pk = _peak(_ncc_shifts(ref, warped, F, (ha, hl), sa2, 1))
    bad = pk < 0.3                                         # decorrelated window: keep the guide there
    d2[bad] = 0.0
    d2 = (d2 + G[F[:, 0], F[:, 1]]).reshape(len(fi), len(fj), 2)
    for c in range(2):
        d2[..., c] = ndimage.median_filter(d2[..., c], size=3, mode="nearest")
    ux, uy = d2[..., 0] * dx, d2[..., 1] * dy
    step = ((fi[1] - fi[0]) * dx if len(fi) > 1 else dx, (fj[1] - fj[0]) * dy if len(fj) > 1 else dy)
    e = lsq_strain(ux, uy, step, (strain_window_mm[0] / step[0] + 1, strain_window_mm[1] / step[1] + 1))
    return _to_pixels(dict(ux=ux, uy=uy, **e), fi, fj, ref.shape)


def _to_pixels(fields: dict, ri, rj, shape) -> dict:
    """Bilinear interpolation of fields sampled at pixel rows ``ri`` / columns ``rj`` onto every pixel; constant
    (nearest sample) outside the sampled box."""
    I, J = np.meshgrid(np.clip(np.arange(shape[0]), ri[0], ri[-1]), np.clip(np.arange(shape[1]), rj[0], rj[-1]),
                       indexing="ij")
    pts = np.column_stack([I.ravel(), J.ravel()])
    out = {}
    for k, v in fields.items():
        if len(ri) < 2 or len(rj) < 2:
            out[k] = np.full(shape, np.nan)
            continue
        f = RegularGridInterpolator((np.asarray(ri, float), np.asarray(rj, float)), v, bounds_error=False,
                                    fill_value=np.nan)
        out[k] = f(pts).reshape(shape)
    return out


def _decimated_envelope(rf, dx, h):
    """Envelope low-passed and resampled from axial spacing ``dx`` to ``h`` mm (anti-aliased)."""
    env = envelope(rf)
    k = max(1, int(round(h / dx)))
    if k > 1:
        env = ndimage.gaussian_filter1d(env, 0.5 * k, axis=0)[::k]
    return env, k


def bspline_sitk(ref, mov, spacing, origin=(0.0, 0.0), *, grid_mm=4.0, iterations=(60, 0), samples=30000,
                 threads: int = 1, seed: int = 1) -> dict:
    """SimpleITK B-spline registration: correlation metric, LBFGS-B, control points every ``grid_mm``.

    Stage 0: an affine transform on envelopes decimated axially to ~0.1 mm, pyramid shrink 4, 2, 1 (smoothing
    2, 1, 0 pixels).  Stage 1: the B-spline on top of it, same images and pyramid, ``iterations[0]`` per level.
    Stage 2 (``iterations[1] > 0``): the B-spline refined on the full-resolution RF; off by default, since it
    changed the total strain error by < 0.1 point at twice the time (1 % / 5 % compression, shear, bending).
    Metric sampled on a random ``min(20 %, samples)`` of the pixels (seeded).  Strain: central differences of
    the dense displacement field (the B-spline field is smooth).
    """
    import SimpleITK as sitk

    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(int(threads))
    ref = np.asarray(ref, float)
    mov = np.asarray(mov, float)
    dx, dy = float(spacing[0]), float(spacing[1])
    x0, y0 = float(origin[0]), float(origin[1])

    def img(a, sx):  # numpy (axial, lateral) -> ITK (x = lateral, y = axial)
        im = sitk.GetImageFromArray(np.ascontiguousarray(a, dtype=np.float64))
        im.SetSpacing((dy, sx))
        im.SetOrigin((y0, x0))
        return im

    er, k = _decimated_envelope(ref, dx, 0.1)
    em, _ = _decimated_envelope(mov, dx, 0.1)
    s = 1.0 / np.std(er)
    fixed_e, moving_e = img(er * s, dx * k), img(em * s, dx * k)
    size_mm = np.array([ref.shape[1] * dy, ref.shape[0] * dx])
    mesh = [max(1, int(round(m / grid_mm))) for m in size_mm]

    def method(tx, levels, n_iter, sigmas, initial=None, n_pixels=er.size):
        R = sitk.ImageRegistrationMethod()
        R.SetMetricAsCorrelation()
        R.SetMetricSamplingStrategy(R.RANDOM)
        R.SetMetricSamplingPercentage(min(0.2, samples / n_pixels), seed)
        R.SetInterpolator(sitk.sitkLinear)
        R.SetOptimizerAsLBFGSB(gradientConvergenceTolerance=1e-6, numberOfIterations=n_iter,
                               maximumNumberOfCorrections=5, maximumNumberOfFunctionEvaluations=4 * n_iter)
        R.SetShrinkFactorsPerLevel(levels)
        R.SetSmoothingSigmasPerLevel(sigmas)
        if initial is not None:
            R.SetMovingInitialTransform(initial)
        R.SetInitialTransform(tx, inPlace=True)
        return R

    # affine first (as elastix users do), then the B-spline on top of it
    affine = sitk.AffineTransform(2)
    affine.SetCenter((y0 + 0.5 * size_mm[0], x0))
    method(affine, [4, 2, 1], 100, [2, 1, 0]).Execute(fixed_e, moving_e)
    tx = sitk.BSplineTransformInitializer(fixed_e, mesh, 3)
    method(tx, [4, 2, 1], iterations[0], [2, 1, 0], affine).Execute(fixed_e, moving_e)
    r = 1.0 / np.std(ref)
    if iterations[1] > 0:
        method(tx, [1], iterations[1], [0], affine, ref.size).Execute(img(ref * r, dx), img(mov * r, dx))
    total = sitk.CompositeTransform(2)
    total.AddTransform(affine)
    total.AddTransform(tx)                    # applied first: p -> affine(tx(p))
    fixed = img(ref, dx)
    disp = sitk.TransformToDisplacementField(total, sitk.sitkVectorFloat64, fixed.GetSize(), fixed.GetOrigin(),
                                             fixed.GetSpacing(), fixed.GetDirection())
    D = sitk.GetArrayFromImage(disp)          # (axial, lateral, [lateral comp, axial comp])
    ux, uy = D[..., 1], D[..., 0]
    gx_ux, gy_ux = np.gradient(ux, dx, dy)
    gx_uy, gy_uy = np.gradient(uy, dx, dy)
    return dict(ux=ux, uy=uy, exx=gx_ux, eyy=gy_uy, exy=0.5 * (gy_ux + gx_uy))


def optical_flow_skimage(ref, mov, spacing, origin=(0.0, 0.0), *, pixel_mm=None, strain_window_mm=3.0,
                         method: str = "tvl1") -> dict:
    """scikit-image optical flow on envelopes resampled to square pixels of ``pixel_mm`` (default
    ``max(2 dx, min(pitch, 0.1))`` mm), least-squares strain over ``strain_window_mm``.

    ``method``: ``"tvl1"`` (:func:`skimage.registration.optical_flow_tvl1`) or ``"ilk"``
    (:func:`skimage.registration.optical_flow_ilk`).  Both use the convention ``ref(x) ~ mov(x + flow(x))``.
    """
    from skimage.registration import optical_flow_ilk, optical_flow_tvl1

    ref = np.asarray(ref, float)
    mov = np.asarray(mov, float)
    dx, dy = float(spacing[0]), float(spacing[1])
    h = float(pixel_mm) if pixel_mm is not None else max(2 * dx, min(dy, 0.1))
    na, nl = ref.shape
    # resample: axial anti-aliased decimation, lateral cubic interpolation onto h
    xi = np.arange(0.0, (na - 1) * dx + 1e-9, h) / dx
    yi = np.arange(0.0, (nl - 1) * dy + 1e-9, h) / dy
    XI, YI = np.meshgrid(xi, yi, indexing="ij")

    def resample(rf):
        env = ndimage.gaussian_filter1d(envelope(rf), max(0.0, 0.5 * h / dx - 0.5), axis=0)
        return ndimage.map_coordinates(env, [XI, YI], order=3, mode="nearest")

    er, em = resample(ref), resample(mov)
    scale = np.percentile(er, 99.5)
    er, em = np.clip(er / scale, 0, 1), np.clip(em / scale, 0, 1)
    if method == "tvl1":
        flow = optical_flow_tvl1(er, em)
    elif method == "ilk":
        flow = optical_flow_ilk(er, em, radius=max(2, int(round(0.5 / h))))
    else:
        raise ValueError(f"method must be 'tvl1' or 'ilk', got {method!r}")
    ux, uy = flow[0] * h, flow[1] * h
    w = strain_window_mm / h
    e = lsq_strain(ux, uy, (h, h), (w, w))
    return _to_pixels(dict(ux=ux, uy=uy, **e), xi, yi, ref.shape)
