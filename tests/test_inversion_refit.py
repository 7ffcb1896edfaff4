"""Region debias refit of the 2D inversion (femreg.inversion.TV_REFIT): the segmentation of the TV solution, the
refit of a soft plane-strain inclusion whose contrast TV shrinks, and the acceptance rule (a region whose shift the
data do not constrain, or whose shift is implausibly large, keeps its TV value).

Ground truth: forward.solve_elasticity (P2 triangles), a different discretisation from the inversion's quads.
"""
from __future__ import annotations

import numpy as np
import pytest

from femreg import inversion
from femreg.inversion import _Regularizer, _regions, _tensor_mesh, invert, modulus_contrast
from test_inversion import solution  # noqa: E402  (shared FE solutions and their cache)

REGION = ((15.0, 45.0), (-15.0, 15.0))
KW = dict(model="plane-strain", region=REGION, element_size=1.5, beta=0.01, uncertainty=False)


def inclusion(points):
    p = np.asarray(points, float)
    return (p[:, 0] - 30.0) ** 2 + p[:, 1] ** 2 < 7.5 ** 2


def soft_disk():
    return solution("plane-strain", 2.5)


def refit_on(monkeypatch, **constants):
    settings = dict(TV_REFIT=0.5, TV_REFIT_MODE="constant-fit", TV_REFIT_MIN_ELEMENTS=4, TV_REFIT_SIGMA=0.1,
                    TV_REFIT_MAX_SHIFT=0.5, TV_REFIT_CAP="reject")
    for k, v in dict(settings, **constants).items():
        monkeypatch.setattr(inversion, k, v)


def test_regions_quantise_connect_and_merge_specks():
    mesh = _tensor_mesh(0.0, 8.0, 0.0, 8.0, (1.0, 1.0))
    reg = _Regularizer(mesh, "tv", 1.0, 64.0)
    c = mesh.p[:, mesh.t].mean(axis=1)
    theta = np.zeros(mesh.t.shape[1])
    blob = (c[0] < 3.0) & (c[1] < 3.0)               # 9 elements at log 1/4
    theta[blob] = np.log(0.25) + 0.05 * np.sin(np.arange(blob.sum()))   # noise below the level
    speck = (c[0] > 6.0) & (c[0] < 7.0) & (c[1] > 6.0) & (c[1] < 8.0)   # 2 elements at log 1.6
    theta[speck] = np.log(1.6)
    labels, cand, core = _regions(theta, reg, 0.5, 4)
    assert len(cand) == 1                              # the blob; the speck joined the background (reference)
    assert np.all(labels[blob] == cand[0]) and np.all(labels[~blob] != cand[0])
    assert np.unique(labels[~blob]).size == 1
    assert np.array_equal(core, ~speck)                # the merged speck is not its region's core
    labels, cand, core = _regions(theta, reg, 0.5, 2)  # a speck of 2 elements is kept with min_elements 2
    assert len(cand) == 2 and core.all()


def test_refit_lifts_the_tv_shrinkage_of_a_soft_plane_strain_disk(monkeypatch):
    sol = soft_disk()
    monkeypatch.setattr(inversion, "TV_REFIT", None)
    tv = modulus_contrast(invert(sol.displacement, **KW), inclusion)["contrast"]
    refit_on(monkeypatch)
    res = invert(sol.displacement, **KW)
    refit = modulus_contrast(res, inclusion)["contrast"]
    assert "region refit (level 0.5): 1 of 1 regions" in res.beta_rule, res.beta_rule
    # measured: debiased TV 0.321 (1.28 x the truth 0.25), refitted 0.267 (1.07 x); 1.5 mm elements, beta 0.01
    assert 0.235 <= refit <= 0.275, f"refitted contrast {refit:.3f} (true 0.25)"
    assert tv - refit >= 0.04, f"TV {tv:.3f}, refitted {refit:.3f}"


def test_refit_keeps_the_tv_value_of_an_unconstrained_or_implausible_region(monkeypatch):
    sol = soft_disk()
    monkeypatch.setattr(inversion, "TV_REFIT", None)
    tv = invert(sol.displacement, **KW)
    # the disk's shift has a measured std of 0.012 (exact data, no registered-field factor): a threshold below it
    # marks the region unconstrained, and it keeps its TV values (the whole image, the only candidate)
    refit_on(monkeypatch, TV_REFIT_SIGMA=0.005)
    res = invert(sol.displacement, **KW)
    assert "region refit (level 0.5): 0 of 1 regions" in res.beta_rule, res.beta_rule
    np.testing.assert_allclose(res.mu, tv.mu, rtol=1e-12)
    # the fitted shift is -0.26: a cap below it rejects the refit, above it accepts it
    refit_on(monkeypatch, TV_REFIT_MAX_SHIFT=0.2)
    res = invert(sol.displacement, **KW)
    assert "region refit (level 0.5): 0 of 1 regions" in res.beta_rule, res.beta_rule
    np.testing.assert_allclose(res.mu, tv.mu, rtol=1e-12)
    refit_on(monkeypatch, TV_REFIT_MAX_SHIFT=0.3)
    res = invert(sol.displacement, **KW)
    assert "region refit (level 0.5): 1 of 1 regions" in res.beta_rule
    assert np.max(np.abs(np.log(res.mu / tv.mu))) > 0.1


@pytest.mark.parametrize("model, tv_ratio, refit_ratio", [("plane-stress", 1.023, 1.055), ("plane-strain", 1.075, 1.015)])
def test_refit_of_a_stiff_disk_from_exact_data_at_a_small_beta(model, tv_ratio, refit_ratio, monkeypatch):
    """At a small beta the TV bias is small and the region model's own error (a constant disk on 1.5 mm quads)
    is of the same size: the stiff plane-stress disk reads higher after the refit, the plane-strain one lower."""
    sol = solution(model, 40.0)
    kw = dict(model=model, region=REGION, element_size=1.5, beta=3e-4, uncertainty=False)
    monkeypatch.setattr(inversion, "TV_REFIT", None)
    tv = modulus_contrast(invert(sol.displacement, **kw), inclusion)["contrast"] / 4.0
    refit_on(monkeypatch)
    refit = modulus_contrast(invert(sol.displacement, **kw), inclusion)["contrast"] / 4.0
    # measured (TV -> refit): plane stress 1.023 -> 1.055, plane strain 1.075 -> 1.015; bounds 0.01 around them
    assert abs(tv - tv_ratio) <= 0.01, tv
    assert abs(refit - refit_ratio) <= 0.01, refit


def test_many_regions_are_not_refitted():
    """A TV solution split into more regions than TV_REFIT_MAX_REGIONS (smoothly varying tissue, not a few
    lesions) keeps its TV values; with at most that many the refit goes on to fit them."""
    from femreg.inversion import _region_refit

    mesh = _tensor_mesh(0.0, 12.0, 0.0, 12.0, (1.0, 1.0))
    reg = _Regularizer(mesh, "tv", 1.0, 144.0)
    c = mesh.p[:, mesh.t].mean(axis=1)
    theta = np.zeros(mesh.t.shape[1])
    blobs = [(i, j) for i in (1.0, 5.0, 9.0) for j in (1.0, 5.0, 9.0)][:8]
    for k, (i, j) in enumerate(blobs):                # 8 blobs of 4 elements at alternating levels
        inside = (c[0] > i) & (c[0] < i + 2.0) & (c[1] > j) & (c[1] < j + 2.0)
        theta[inside] = 0.8 if k % 2 else -0.8
    out, diag = _region_refit(None, None, reg, theta, 100, 1.0, level=0.5, min_elements=4, sigma_max=0.1,
                              max_shift=0.5, max_regions=5)
    assert diag["too_many"] and diag["regions"] == 9 and out is theta
    with pytest.raises(AttributeError):          # at most 8 allowed: it goes on to the fit (fem needed)
        _region_refit(None, None, reg, theta, 100, 1.0, level=0.5, min_elements=4, sigma_max=0.1,
                      max_shift=0.5, max_regions=8)
