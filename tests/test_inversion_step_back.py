"""The dof rule's step back (femreg.inversion.DOF_STEP_BACK): where the beta nearest the target is the bracket's
smaller one and its image shows more than the data support, the bracket's larger beta is taken.

References: images built here on a tensor mesh with a strain that supports them or not (a stiff disk straining 1/4
as much as its background, layers at one strain, a speckle of levels), and the forward model's exact displacement
(forward.solve_elasticity, P2 triangles) with seeded white noise of a known level.
"""
from __future__ import annotations

import numpy as np
import pytest

import femreg.inversion as inversion
from femreg.inversion import _overfit_reason, _Regularizer, _tensor_mesh

H = 1.5


def _image(kind):
    """(theta, el_strain, mesh, reg, area) of a 30 x 30 mm tensor mesh of 1.5 mm elements: ``"disk"`` a stiff
    disk (x4, radius 6 mm) whose abs(e_xx) is 1/4 of the background's; ``"layers"`` the deeper half 2 x stiffer at
    one strain; ``"speckle"`` ten 4.5 mm squares at alternating levels x1.8 / x0.55, each straining 1 / its
    modulus (supported, but no few regions)."""
    mesh = _tensor_mesh(0.0, 30.0, -15.0, 15.0, (H, H))
    c = mesh.p[:, mesh.t].mean(axis=1)
    n = c.shape[1]
    theta = np.zeros(n)
    if kind == "disk":
        theta[(c[0] - 15.0) ** 2 + c[1] ** 2 < 36.0] = np.log(4.0)
    elif kind == "layers":
        theta[c[0] > 15.0] = np.log(2.0)
    else:
        k = 0
        for x0 in (3.0, 12.0, 21.0):
            for y0 in (-12.0, -3.0, 6.0):
                sel = (c[0] >= x0) & (c[0] < x0 + 4.5) & (c[1] >= y0) & (c[1] < y0 + 4.5)
                theta[sel] = np.log(1.8) if k % 2 == 0 else np.log(0.55)
                k += 1
    strain = np.zeros((n, 3))
    strain[:, 0] = -0.01 * np.exp(-theta)     # |e_xx| falls with the modulus, as in series
    strain[:, 1] = 0.01 * np.exp(-theta)
    if kind == "layers":
        strain[:, 0], strain[:, 1] = -0.01, 0.01     # one strain: the layers are not in the data
    area = np.full(n, H * H)
    reg = _Regularizer(mesh, "tv", H, 900.0)
    return theta, strain, mesh, reg, area


def test_overfit_reason_passes_a_supported_disk():
    theta, strain, mesh, reg, area = _image("disk")
    assert _overfit_reason(theta, None, False, reg, strain, mesh, area, H) == ""


def test_overfit_reason_names_layers_at_one_strain():
    theta, strain, mesh, reg, area = _image("layers")
    assert _overfit_reason(theta, None, False, reg, strain, mesh, area, H) == "its modulus contradicts the strain"


def test_overfit_reason_names_an_image_of_many_regions():
    theta, strain, mesh, reg, area = _image("speckle")
    why = _overfit_reason(theta, None, False, reg, strain, mesh, area, H)
    assert why.startswith("its TV image has 9 regions besides the largest"), why
    # the result's theta is read for the strain check, the TV solution (theta_part) for the regions
    disk = _image("disk")[0]
    assert _overfit_reason(theta, disk, False, reg, strain, mesh, area, H) == ""


def test_unsupported_region_takes_the_background_level(monkeypatch):
    """SUPPORT_MERGE end to end on the exact stiff disk x4 (plane stress, 3 mm elements, beta 0.01): its disk
    strains about 0.4 x the background, supported, and comes out near 4 with or without the merge.  With
    SUPPORT_FRACTION raised past that ratio the disk counts as unsupported: it takes the background's level (contrast
    within 0.1 of 1; 3.9 without the merge), ``unsupported_area`` still reports the TV solution's region, a note
    says it was set to the background, and the misfit flag says the model no longer explains the data."""
    from test_inversion import REGION, inclusion, solution

    from femreg.inversion import UNSUPPORTED_AREA, invert, modulus_contrast

    sol = solution("plane-stress", 40.0)
    kw = dict(region=REGION, element_size=3.0, beta=0.01, uncertainty=False)
    clean = invert(sol.displacement, **kw)
    c_clean = modulus_contrast(clean, inclusion)["contrast"]
    assert clean.success and not clean.notes and 3.5 < c_clean < 4.5, (c_clean, clean.notes)
    monkeypatch.setattr(inversion, "SUPPORT_FRACTION", 5.0)
    monkeypatch.setattr(inversion, "SUPPORT_MERGE", False)
    kept = invert(sol.displacement, **kw)
    assert modulus_contrast(kept, inclusion)["contrast"] == pytest.approx(c_clean, rel=1e-9)
    monkeypatch.setattr(inversion, "SUPPORT_MERGE", True)
    merged = invert(sol.displacement, **kw)
    c = modulus_contrast(merged, inclusion)["contrast"]
    assert abs(c - 1.0) < 0.1, c
    # a true contrast set to the background leaves a misfit the model cannot explain: flagged (measured 1.04)
    assert not merged.success and any("does not explain the data" in f for f in merged.flags), merged.flags
    assert merged.unsupported_area == pytest.approx(kept.unsupported_area)
    assert merged.unsupported_area > UNSUPPORTED_AREA
    assert any("set to the background's level" in n for n in merged.notes), merged.notes
    assert "set to the background's level, refit again" in merged.beta_rule


def _soft_noisy():
    """The soft plane-strain disk (x0.25) of tests/test_inversion.py with white noise of 1 um (5 um laterally) at
    the nodes of the 3 mm mesh: the rule's target (21.0 parameters) lies between gamma 17.0 at beta 0.01 and 25.1
    at 0.00316, the nearer the smaller (measured)."""
    from test_inversion import solution
    from test_inversion_rules import _noisy

    return _noisy(solution("plane-strain", 2.5), 1e-3)


def test_rule_steps_back_to_the_larger_beta_of_the_bracket(monkeypatch):
    """With the smaller beta's image failing (a stand-in for _overfit_reason's tests) the rule takes the bracket's
    larger beta, says why, and the uncertainty comes from that beta; without a failure, or with DOF_STEP_BACK off,
    the nearer (smaller) one.  Where the larger fails too, the smaller is kept and the rule says it was tried."""
    from test_inversion import REGION

    from femreg.inversion import invert

    f = _soft_noisy()
    kw = dict(region=REGION, element_size=3.0)
    plain = invert(f, uncertainty=False, **kw)
    assert plain.beta == pytest.approx(10 ** -2.5) and "stepped back" not in plain.beta_rule, plain.beta_rule
    target_side = [e["gamma"] for e in plain.sweep if e["beta"] in (1e-2, plain.beta)]
    assert target_side[0] < 21.0 <= target_side[1], plain.sweep       # the bracket 0.01 / 0.00316
    calls = []

    def first_fails(*a, **k):
        calls.append(a[0].copy())
        return "a stand-in reason" if len(calls) == 1 else ""

    monkeypatch.setattr(inversion, "_overfit_reason", first_fails)
    back = invert(f, **kw)
    assert back.beta == pytest.approx(1e-2) and len(calls) == 2
    assert "stepped back to the bracket's larger beta 0.01" in back.beta_rule and "a stand-in reason" in back.beta_rule
    assert back.uncertainty is not None and np.isfinite(back.uncertainty[back.constrained]).all()
    monkeypatch.setattr(inversion, "DOF_STEP_BACK", False)
    calls.clear()
    assert invert(f, uncertainty=False, **kw).beta == pytest.approx(plain.beta) and not calls
    monkeypatch.setattr(inversion, "DOF_STEP_BACK", True)
    monkeypatch.setattr(inversion, "_overfit_reason", lambda *a, **k: "always")
    kept = invert(f, uncertainty=False, **kw)
    assert kept.beta == pytest.approx(plain.beta) and "was tried too (always) and not taken" in kept.beta_rule
    assert np.allclose(kept.mu, plain.mu, rtol=1e-9, atol=0)     # the smaller beta's image, as without the try


def test_rule_steps_back_to_a_beta_above_the_grid(monkeypatch):
    """The bracket's larger beta may come from the half-decade steps above the grid (DOF_UP_STEPS: more parameters
    than the target already at the grid's largest beta, as on fine meshes).  With the grid starting at 0.00316 the
    soft disk's target (21.0) lies between that beta (25.1, the nearer) and the step above it, 0.01 (17.0): where
    the smaller one's image fails, the rule takes 0.01 from those steps, as it does inside the grid."""
    from test_inversion import REGION

    from femreg.inversion import invert

    f = _soft_noisy()
    kw = dict(region=REGION, element_size=3.0, uncertainty=False)
    monkeypatch.setattr(inversion, "BETA_GRID", tuple(10.0 ** e for e in np.arange(-2.5, -4.01, -0.5)))
    plain = invert(f, **kw)
    assert plain.beta == pytest.approx(10 ** -2.5) and "stepped back" not in plain.beta_rule, plain.beta_rule
    assert any(e["beta"] == pytest.approx(1e-2) for e in plain.sweep), plain.sweep       # solved by the up-steps
    calls = []

    def first_fails(*a, **k):
        calls.append(1)
        return "a stand-in reason" if len(calls) == 1 else ""

    monkeypatch.setattr(inversion, "_overfit_reason", first_fails)
    back = invert(f, **kw)
    assert back.beta == pytest.approx(1e-2) and len(calls) == 2, back.beta_rule
    assert "stepped back to the bracket's larger beta 0.01" in back.beta_rule
