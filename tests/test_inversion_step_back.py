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
    disk (x4, radius 6 mm) whose |e_xx| is 1/4 of the background's; ``"layers"`` the deeper half 2 x stiffer at
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
    within 0.1 of 1; 3.9 without the merge), ``unsupported_area`` still reports the TV solution's region and a note
    says it was set to the background."""
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
    assert merged.success and abs(c - 1.0) < 0.1, c
    assert merged.unsupported_area == pytest.approx(kept.unsupported_area)
    assert merged.unsupported_area > UNSUPPORTED_AREA
    assert any("set to the background's level" in n for n in merged.notes), merged.notes
    assert "set to the background's level, refit again" in merged.beta_rule
