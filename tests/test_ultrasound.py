"""RF simulator (forward/ultrasound.py): every property measured from simulated images, not from the parameters."""
import math

import numpy as np
import pytest
from scipy.ndimage import map_coordinates, spline_filter
from scipy.optimize import curve_fit, minimize_scalar

from forward.ultrasound import (PSF, ImagingGrid, add_noise, bmode, envelope, make_scatterers, measured_snr_db,
                                render_rf)

PAPER_PSF = PSF()
F0 = 5.5e6


def speckle(depth=20.0, width=12.0, seed=0, density=30.0, inclusion=False):
    """Noise-free speckle image of a homogeneous (or with inclusion) scatterer field, plus its scatterers."""
    grid = ImagingGrid.centred(depth_mm=depth, width_mm=width)
    x0, x1, y0, y1 = grid.extent()
    box = (x0 - 1.0, x1 + 1.0, y0 - 3.0, y1 + 3.0)
    scat = make_scatterers(np.random.default_rng(seed), box, density_per_mm2=density,
                           inclusion_center=(depth / 2, 0.0), inclusion_radius_mm=2.0 if inclusion else None)
    return grid, scat, render_rf(scat.positions, scat.amplitudes, grid)


def subsample_lag(a, b, axis, margin=12):
    """Lag ``tau`` (samples) maximising the normalised cross-correlation
    ``c(tau) = sum_n a[n] b(n + tau) / sqrt(sum_n b(n + tau)^2)`` along ``axis``
    (summed over the other axis and over the interior ``n`` at least ``margin`` samples from the ends).  Integer
    peak from the FFT correlation, then sub-sample refinement maximising ``c`` with ``b(n + tau)`` from a
    quintic B-spline interpolant of ``b``.  If ``b`` is ``a`` moved by ``+d`` samples, the result is ``d``."""
    a = np.moveaxis(np.asarray(a, float), axis, 0)
    b = np.moveaxis(np.asarray(b, float), axis, 0)
    n = a.shape[0]
    m = 2 * n
    c = np.fft.ifft((np.conj(np.fft.fft(a, m, axis=0)) * np.fft.fft(b, m, axis=0)).sum(axis=1)).real
    p = int(np.argmax(c))
    p = p - m if p > m // 2 else p
    coef = spline_filter(b, order=5, mode="mirror")
    rows = np.arange(margin, n - margin, dtype=float)
    R, C = np.meshgrid(rows, np.arange(b.shape[1], dtype=float), indexing="ij")
    a_in = a[margin:n - margin]

    def neg_corr(t):
        bt = map_coordinates(coef, [R + t, C], order=5, prefilter=False, mode="mirror")
        return -float(np.sum(a_in * bt)) / math.sqrt(float(np.sum(bt * bt)))  # normalised (NCC)

    return minimize_scalar(neg_corr, bounds=(p - 1, p + 1), method="bounded", options={"xatol": 1e-6}).x


def test_paper_grid_spacing_and_shape():
    grid = ImagingGrid.centred()
    # c / (2 fs) = 1540 m/s / 80 MHz
    assert grid.dx == pytest.approx(0.01925, rel=1e-12)
    assert grid.dy == 0.3
    assert grid.shape == (3740, 147), grid.shape
    assert grid.origin == (0.0, pytest.approx(-21.9))
    assert grid.y[-1] == pytest.approx(21.9)


def test_centre_frequency_from_axial_spectrum():
    grid, _, rf = speckle()
    fs = PAPER_PSF.speed_of_sound_mm_per_s / (2 * grid.dx)  # axial sampling rate in echo time, Hz
    win = np.hanning(rf.shape[0])[:, None]
    power = (np.abs(np.fft.rfft(rf * win, axis=0)) ** 2).mean(axis=1)
    f = np.fft.rfftfreq(rf.shape[0], d=1 / fs)
    centroid = float(np.sum(f * power) / np.sum(power))
    # Gaussian fit to the averaged power spectrum: its centre is the peak frequency without periodogram noise.
    (_, fc, _), _ = curve_fit(lambda f, a, m, s: a * np.exp(-0.5 * ((f - m) / s) ** 2), f / 1e6, power,
                              p0=(power.max(), f[np.argmax(power)] / 1e6, 1.0))
    assert abs(centroid / F0 - 1) < 0.02, f"spectral centroid {centroid / 1e6:.4f} MHz"
    assert abs(fc * 1e6 / F0 - 1) < 0.02, f"fitted spectral peak {fc:.4f} MHz"


def _isolated_scatterer_envelope(y_s=0.1234, x_s=5.0037):
    grid = ImagingGrid.centred(depth_mm=10.0, width_mm=9.0)
    rf = render_rf([[x_s, y_s]], [1.0], grid)
    return grid, envelope(rf)


def test_lateral_fwhm_of_isolated_scatterer():
    grid, env = _isolated_scatterer_envelope()
    i, _ = np.unravel_index(np.argmax(env), env.shape)
    prof = env[i]

    def gauss(y, a, mu, s):
        return a * np.exp(-0.5 * ((y - mu) / s) ** 2)

    (a, mu, s), _ = curve_fit(gauss, grid.y, prof, p0=(prof.max(), grid.y[np.argmax(prof)], 0.5))
    fwhm = 2 * math.sqrt(2 * math.log(2)) * abs(s)
    assert abs(fwhm / 1.4 - 1) < 0.05, f"lateral FWHM {fwhm:.4f} mm (fitted Gaussian to sampled envelope)"
    assert abs(mu - 0.1234) < 0.01, f"lateral peak at {mu:.4f} mm, scatterer at 0.1234 mm"


def test_axial_envelope_duration_is_the_stated_pulse_length():
    # Docstring: pulse length 0.43 us = -6 dB duration of the envelope in echo time (t = 2 x / c).
    grid, env = _isolated_scatterer_envelope()
    _, j = np.unravel_index(np.argmax(env), env.shape)
    col = env[:, j] / env[:, j].max()
    above = np.flatnonzero(col >= 0.5)
    lo, hi = above[0], above[-1]
    # linear interpolation of the half-maximum crossings (17 samples per FWHM)
    x_lo = lo - (col[lo] - 0.5) / (col[lo] - col[lo - 1])
    x_hi = hi + (col[hi] - 0.5) / (col[hi] - col[hi + 1])
    fwhm_mm = (x_hi - x_lo) * grid.dx
    duration_us = 2 * fwhm_mm / PAPER_PSF.speed_of_sound_mm_per_s * 1e6
    assert abs(duration_us / 0.43 - 1) < 0.03, f"-6 dB envelope duration {duration_us:.4f} us"


def test_snr_of_added_noise():
    _, _, clean = speckle(seed=1)
    for snr in (12.0, 3.0):
        noisy = add_noise(clean, snr, np.random.default_rng(5))
        meas = measured_snr_db(clean, noisy)
        assert abs(meas - snr) < 0.5, f"requested {snr} dB, measured {meas:.3f} dB"


def test_fully_developed_speckle_envelope_snr_is_rayleigh():
    # Envelope mean/std over three homogeneous 30 x 30 mm images (estimator std ~0.017 for the average), without
    # noise and at 12 dB.  Stratified placement at 30 per mm^2 measures ~1.88 (independent placement ~1.81).
    rayleigh = math.sqrt(math.pi / (4 - math.pi))  # 1.913
    psf = PSF()
    clean_v, noisy_v = [], []
    for seed in range(3):
        grid = ImagingGrid.centred(depth_mm=30.0, width_mm=30.0)
        x0, x1, y0, y1 = grid.extent()
        scat = make_scatterers(np.random.default_rng(seed), (x0 - 1, x1 + 1, y0 - 3, y1 + 3),
                               inclusion_radius_mm=None, cell_aspect=psf.sigma_axial_mm / psf.sigma_lateral_mm)
        rf = render_rf(scat.positions, scat.amplitudes, grid)
        for rf_, out in ((rf, clean_v), (add_noise(rf, 12.0, np.random.default_rng(10 + seed)), noisy_v)):
            env = envelope(rf_)[100:-100, 5:-5]  # away from the Hilbert transform's ends and the sides
            out.append(env.mean() / env.std())
    for name, v in (("clean", clean_v), ("12 dB", noisy_v)):
        assert abs(np.mean(v) - rayleigh) < 0.08, f"{name}: envelope mean/std {np.round(v, 3)}, Rayleigh 1.913"


@pytest.mark.parametrize("axis,d", [(0, 0.3), (0, -0.77), (1, 0.4), (1, -0.25)])
def test_rigid_subsample_shift_moves_the_image(axis, d):
    grid, scat, rf0 = speckle(depth=8.0, width=10.0, seed=4)
    step = grid.spacing[axis]
    moved = scat.positions.copy()
    moved[:, axis] += d * step
    rf1 = render_rf(moved, scat.amplitudes, grid)
    lag = subsample_lag(rf0, rf1, axis)
    assert abs(lag - d) < 0.05, f"axis {axis}: shift {d} samples, measured {lag:.4f} samples"


def test_rendering_is_linear_and_exact_at_pixel_centres():
    grid = ImagingGrid.centred(depth_mm=2.0, width_mm=3.0)
    x, y = grid.x[40], grid.y[5]
    rf = render_rf([[x, y]], [2.5], grid)
    assert rf[40, 5] == pytest.approx(2.5, rel=1e-12)  # peak of h_ax * h_lat is 1
    rf2 = render_rf([[x, y], [x + 0.0031, y - 0.07]], [2.5, -1.0], grid)
    rf3 = render_rf([[x + 0.0031, y - 0.07]], [-1.0], grid)
    assert np.abs(rf2 - rf - rf3).max() < 1e-12


def test_bmode_range_and_reference():
    _, _, rf = speckle(depth=5.0, width=5.0)
    b = bmode(rf, 40.0)
    assert b.max() == pytest.approx(0.0) and b.min() >= -40.0
    assert np.isclose(b, -40.0).mean() < 0.2, "log compression clips most of the image"


@pytest.mark.parametrize("call,name", [
    (lambda: make_scatterers(np.random.default_rng(0), (0, 1, 0, 1), density_per_mm2=-1.0), "density"),
    (lambda: make_scatterers(np.random.default_rng(0), (0, 1, 0, 1), density_per_mm2=float("nan")), "density"),
    (lambda: add_noise(np.ones((4, 4)), float("inf"), np.random.default_rng(0)), "snr_db"),
    (lambda: add_noise(np.ones((4, 4)), float("nan"), np.random.default_rng(0)), "snr_db"),
    (lambda: ImagingGrid.centred(spacing=(0.0, 0.3)), "spacing"),
    (lambda: ImagingGrid.centred(spacing=(0.02, -0.3)), "spacing"),
    (lambda: ImagingGrid(10, 10, 0.02, 0.0), "spacing"),
    (lambda: PSF(center_frequency_hz=-5e6), "center_frequency_hz"),
    (lambda: PSF(lateral_fwhm_mm=0.0), "lateral_fwhm_mm"),
    (lambda: render_rf([[0.0, np.nan]], [1.0], ImagingGrid(4, 4, 0.02, 0.3)), "finite"),
])
def test_bad_input_raises_value_error_naming_it(call, name):
    with pytest.raises(ValueError, match=name):
        call()
