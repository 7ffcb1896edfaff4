"""The scatter floor on a calibrated 2D TV uncertainty (femreg.inversion.SCATTER_FLOOR): the Laplace std times
max(1, robust spread of log mu over the background / RMS of its std).  Correlated noise in the displacement (as a
registration's: errors shared by neighbouring nodes) leaves a background texture wider than the Laplace std, which
takes the nodal data as independent; the floor widens the std to that texture, never narrows it, and leaves the
modulus alone.  Off where the calibration is not assessed (Tikhonov, 3D) or fails (the bias term of
UNCALIBRATED_SPREAD instead).

Ground truth: forward.solve_elasticity (P2 triangles), a different discretisation from the inversion's quads.
"""
from __future__ import annotations

import numpy as np
import pytest

from femreg import inversion
from femreg.inversion import _scatter_factor, invert, load_inversion

from test_inversion import REGION, inclusion, solution  # noqa: E402  (shared FE solutions and their cache)
from test_inversion3d import _layers  # noqa: E402

KW = dict(model="plane-stress", region=REGION, element_size=1.5, beta=0.01)
_FIELDS = {}


def noisy(amplitude, seed, corr=1.0, step=0.25):
    """The stiff disk's (x4, plane stress) exact displacement plus noise of ``amplitude`` mm per component,
    Gaussian-correlated over ``corr`` mm (white noise on a ``step`` grid, smoothed, unit std, interpolated)."""
    from scipy.interpolate import RegularGridInterpolator
    from scipy.ndimage import gaussian_filter

    key = (amplitude, seed, corr)
    if key not in _FIELDS:
        sol = solution("plane-stress", 40.0)
        rng = np.random.default_rng(seed)
        gx = np.arange(REGION[0][0] - 1.0, REGION[0][1] + 1.0 + 1e-9, step)
        gy = np.arange(REGION[1][0] - 1.0, REGION[1][1] + 1.0 + 1e-9, step)
        comps = []
        for _ in range(2):
            n = gaussian_filter(rng.standard_normal((gx.size, gy.size)), corr / step)
            comps.append(RegularGridInterpolator((gx, gy), n / n.std()))

        def f(p):
            p = np.asarray(p, float)
            return sol.displacement(p) + amplitude * np.column_stack([c(p) for c in comps])
        _FIELDS[key] = f
    return _FIELDS[key]


def within(res, contrast=4.0):
    """Fraction of the constrained elements whose true log mu (the disk's contrast at the centre, else 1) lies
    within +-1 sigma (benchmarks/inversion.py's count)."""
    ok = np.isfinite(res.uncertainty)
    true = np.where(inclusion(res.centroids), np.log(contrast), 0.0)
    return float(np.mean(np.abs(np.log(res.mu[ok]) - true[ok]) <= res.uncertainty[ok]))


def pair(monkeypatch, field, **kw):
    monkeypatch.setattr(inversion, "SCATTER_FLOOR", False)
    off = invert(field, **dict(KW, **kw))
    monkeypatch.setattr(inversion, "SCATTER_FLOOR", True)
    return off, invert(field, **dict(KW, **kw))


@pytest.mark.parametrize("seed", [0, 2])
def test_floor_widens_an_under_covering_std_to_the_background_scatter(monkeypatch, seed):
    off, on = pair(monkeypatch, noisy(1e-3, seed))
    assert off.uncertainty_calibrated and on.uncertainty_calibrated
    assert off.uncertainty_scale is None
    # the modulus is the same solve; the std only is scaled, everywhere by the one factor
    np.testing.assert_array_equal(on.mu, off.mu)
    ok = np.isfinite(off.uncertainty)
    np.testing.assert_array_equal(np.isfinite(on.uncertainty), ok)
    np.testing.assert_allclose(on.uncertainty[ok], on.uncertainty_scale * off.uncertainty[ok], rtol=1e-12)
    # measured: factor 1.83 / 1.78, within +-1 sigma 34 -> 56 % / 32 -> 49 % (1 um, 1 mm correlation, 1.5 mm
    # elements); bounds with margins
    assert on.uncertainty_scale > 1.5, on.uncertainty_scale
    assert within(off) < 0.40 and within(on) > within(off) + 0.12, (within(off), within(on))
    # the background's std now matches its robust scatter (the factor's definition, read back from the result)
    from femreg.inversion import _calibration_partition, _Regularizer, _robust_spread

    reg = _Regularizer(on.mesh, "tv", 1.0, 900.0)
    labels, cand = _calibration_partition(np.log(on.mu), reg, 1.5 * 1.5)
    bg = ~np.isin(labels, cand) & ok
    rms = np.sqrt(np.mean(on.uncertainty[bg] ** 2))
    assert rms == pytest.approx(_robust_spread(np.log(on.mu[bg])), rel=0.05)


def test_floor_never_narrows_and_is_kept_in_the_file(monkeypatch, tmp_path):
    # half the noise, another seed: the Laplace std covers the background's scatter (measured factor 1.0)
    off, on = pair(monkeypatch, noisy(5e-4, 1))
    assert on.uncertainty_scale == 1.0
    ok = np.isfinite(off.uncertainty)
    assert np.all(on.uncertainty[ok] >= off.uncertainty[ok])
    back = load_inversion(on.save(tmp_path / "mu.npz"))
    assert back.uncertainty_scale == on.uncertainty_scale
    np.testing.assert_array_equal(back.uncertainty, on.uncertainty)


def test_scatter_factor_is_at_least_one():
    rng = np.random.default_rng(1)
    n = 200
    labels = np.zeros(n, int)
    labels[:30] = 1                             # a disk region, left out of the background
    theta = np.where(labels == 1, 1.4, 0.0) + 0.1 * rng.standard_normal(n)
    constrained = np.ones(n, bool)
    # std far above the scatter: 1, not below
    assert _scatter_factor(theta, np.full(n, 1.0), labels, [1], constrained) == 1.0
    # std a fifth of the scatter: about 5 (the robust spread of the 170 background values, not the disk's step)
    f = _scatter_factor(theta, np.full(n, 0.02), labels, [1], constrained)
    assert 3.5 < f < 6.5, f
    # too few background elements with a finite std: 1
    std = np.full(n, np.nan)
    std[:35] = 0.02
    assert _scatter_factor(theta, std, labels, [1], constrained) == 1.0


def test_off_for_tikhonov_3d_and_uncalibrated_images(monkeypatch):
    # Tikhonov: the calibration is not assessed, no floor
    off, on = pair(monkeypatch, noisy(1e-3, 0), regularization="tikhonov", beta=1e-3)
    assert on.uncertainty_scale is None and on.uncertainty_calibrated is None
    np.testing.assert_array_equal(on.uncertainty, off.uncertainty)
    # an image of many regions (2 um of correlated noise): uncalibrated, the bias term, no floor
    off, on = pair(monkeypatch, noisy(2e-3, 0))
    assert on.uncertainty_calibrated is False and on.uncertainty_scale is None
    np.testing.assert_array_equal(on.uncertainty, off.uncertainty)
    # 3D
    kw3 = dict(region=(0.0, 12.0, -3.0, 3.0, -3.0, 3.0), element_size=2.0, beta=1e-3)
    monkeypatch.setattr(inversion, "SCATTER_FLOOR", False)
    off = invert(_layers(2.0), **kw3)
    monkeypatch.setattr(inversion, "SCATTER_FLOOR", True)
    on = invert(_layers(2.0), **kw3)
    assert on.uncertainty_scale is None and on.uncertainty is not None
    np.testing.assert_array_equal(on.uncertainty, off.uncertainty)
