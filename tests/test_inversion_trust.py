"""Modulus inversion a user can trust: the model follows the data, flags instead of silently wrong results,
the uncertainty map (Laplace approximation), absolute stiffness from a reference region.

Ground truth: forward.solve_elasticity (P2 triangles), a different discretisation from the inversion's quads.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

import femreg
from femreg.errors import InputError
from femreg.inversion import (_contradiction, _element_strain, _tensor_mesh, invert, load_inversion,
                              modulus_contrast)

from test_inversion import FE, REGION, inclusion, solution  # noqa: E402  (shared FE solutions and their cache)


# ------------------------------------------------------------------------------------------------------------
# the model follows the data
# ------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("truth", ["plane-strain", "plane-stress"])
def test_auto_model_follows_the_data(truth):
    res = invert(solution(truth, 40.0).displacement, region=REGION, element_size=1.5, beta=3e-4)
    # measured strain ratio -e_yy / e_xx: 0.98 (plane strain, nu 0.495), 0.49-0.52 (plane stress)
    assert res.model == truth, (res.model_rule, res.strain_ratio)
    expected = 0.98 if truth == "plane-strain" else 0.5
    assert abs(res.strain_ratio - expected) < 0.05, res.strain_ratio
    assert res.model_rule.startswith("auto")
    c = modulus_contrast(res, inclusion)["contrast"]
    assert abs(c / 4 - 1) < 0.1, c          # measured 4.09 (plane stress), 4.31 (plane strain, 1.5 mm)


def test_effective_lambda_between_the_models():
    from femreg.inversion import _auto_model, model_ratio

    name, lb, _, rule = _auto_model(0.8)
    assert name == "effective" and abs(model_ratio(lb) - 0.8) < 1e-12 and 2 < lb < 99
    assert _auto_model(0.5)[0] == "plane-stress" and _auto_model(0.97)[0] == "plane-strain"


def test_explicit_wrong_model_is_flagged():
    """Plane-stress inversion of exact plane-strain data: the model is wrong, and the result says so."""
    sol = solution("plane-strain", 40.0)
    res = invert(sol.displacement, model="plane-stress", region=REGION, element_size=1.5, beta=3e-4)
    c = modulus_contrast(res, inclusion)["contrast"]
    assert c < 3.4                       # the wrong model does give a wrong contrast (measured 2.7-3.0) ...
    assert not res.success and "strain ratio" in res.message   # ... and it is flagged
    right = invert(sol.displacement, model="plane-strain", region=REGION, element_size=1.5, beta=3e-4)
    assert right.success and not right.flags


@pytest.mark.parametrize("lateral, flagged", [(0.95, False), (0.87, True)])
def test_explicit_model_against_a_shrunk_lateral_strain(lateral, flagged, monkeypatch):
    """The exact plane-strain field with its lateral displacement scaled (as a registration that smooths the lateral
    strain, R_eps: ratio 0.85 against the truth's 0.98) and model='plane-strain' given: 0.95 (ratio 0.93, the size of
    the largest registered deviation on benchmarks/inversion.py, 0.047) stays unflagged and in the band; 0.87 (ratio
    0.85) contradicts the model by more than RATIO_TOLERANCE and is flagged, its contrast wrong."""
    from femreg import inversion
    from femreg.inversion import RATIO_TOLERANCE

    # the model check, without the region refit (which reads the flagged 0.87 case at 4.20, closer to the truth)
    monkeypatch.setattr(inversion, "TV_REFIT", None)
    sol = solution("plane-strain", 40.0)
    res = invert(lambda p: sol.displacement(p) * np.array([1.0, lateral]), model="plane-strain", region=REGION,
                 element_size=1.5, beta=3e-4, uncertainty=False)
    c = modulus_contrast(res, inclusion)["contrast"]
    # measured: ratio 0.929 / 0.851, contrast 3.58 / 3.16 (true 4; 4.30 unscaled)
    assert abs(res.strain_ratio - 0.98 * lateral) < 0.01, res.strain_ratio
    assert (abs(res.strain_ratio - 0.98) > RATIO_TOLERANCE) == flagged
    if flagged:
        assert not res.success and "contradicts the plane-strain model" in res.message
        assert abs(c / 4 - 1) > 0.15, c
    else:
        assert res.success and not res.flags and abs(c / 4 - 1) < 0.15, (c, res.flags)


def test_beta_on_the_grid_edge_is_flagged():
    sol = solution("plane-stress", 40.0)
    res = invert(sol.displacement, region=REGION, element_size=3.0, beta_grid=(0.1, 0.01, 1e-3),
                 beta_method="growth")
    # exact data: the regulariser never grows quickly, the growth rule ends on the smallest beta (the default rule's
    # edges: tests/test_inversion_rules.py)
    assert res.beta == 1e-3 and not res.success
    assert any("edge" in f for f in res.flags) and "edge" in res.beta_rule


def test_modulus_against_strain_is_flagged():
    """A disk that strains less than its surroundings but is shown softer is flagged; shown stiffer, not."""
    sol = solution("plane-stress", 40.0)
    mesh = _tensor_mesh(15.0, 45.0, -15.0, 15.0, (1.5, 1.5))
    res = invert(sol.displacement, region=REGION, element_size=1.5, beta=3e-4, uncertainty=False)
    el = res.strain_measured
    area = np.full(mesh.t.shape[1], 2.25)
    inside = inclusion(res.centroids)
    right = np.where(inside, 4.0, 1.0)
    assert _contradiction(right, el, res.mesh, area) == ""
    why = _contradiction(1.0 / right, el, res.mesh, area)
    assert "soft region" in why and "strains less" in why


def test_a_small_contrast_on_the_wrong_side_is_flagged():
    """The exact field of the 4x disk: a disk shown 25 % softer (no element beyond CONTRAST_REGION, which the regions'
    test needs) contradicts the strain and is flagged; shown 25 % stiffer it is not, nor is seeded noise of 1-3 %."""
    from skfem import Basis, ElementQuad1, ElementVector

    from femreg.inversion import CONTRAST_REGION

    sol = solution("plane-stress", 40.0)
    mesh = _tensor_mesh(15.0, 45.0, -15.0, 15.0, (1.5, 1.5))
    v = sol.displacement(mesh.p.T)
    d = np.column_stack([v[:, 0], v[:, 1]]).ravel()
    el, _ = _element_strain(Basis(mesh, ElementVector(ElementQuad1()), intorder=2), d)
    area = np.full(mesh.t.shape[1], 2.25)
    inside = inclusion(mesh.p[:, mesh.t].mean(axis=1).T)
    wrong = np.where(inside, 0.8, 1.0)
    assert np.all((wrong < CONTRAST_REGION) & (wrong > 1 / CONTRAST_REGION))
    why = _contradiction(wrong, el, mesh, area)
    assert "stiffer part" in why and "other side of 1" in why, why
    assert _contradiction(np.where(inside, 1.25, 1.0), el, mesh, area) == ""
    rng = np.random.default_rng(0)
    for s in (0.01, 0.03):
        assert _contradiction(np.exp(s * rng.standard_normal(mesh.t.shape[1])), el, mesh, area) == ""


# ------------------------------------------------------------------------------------------------------------
# uncertainty
# ------------------------------------------------------------------------------------------------------------
def _noisy(sol, mesh, seed):
    rng = np.random.default_rng(seed)
    noise = {tuple(np.round(x, 6)): rng.standard_normal(2) for x in mesh.p.T}

    def f(p):
        return sol.displacement(p) + np.array([2e-3, 1e-2]) * np.array([noise[tuple(np.round(x, 6))] for x in p])

    return f


def test_uncertainty_matches_the_spread_over_noise_realisations():
    sol = solution("plane-stress", 40.0)
    mesh = _tensor_mesh(15.0, 45.0, -15.0, 15.0, (3.0, 3.0))
    logs, sds = [], []
    for seed in range(8):
        r = invert(_noisy(sol, mesh, seed), region=REGION, element_size=3.0, beta=1e-2)
        logs.append(np.log(r.mu))
        sds.append(r.uncertainty)
    emp = np.std(logs, axis=0, ddof=1)
    pred = np.nanmean(sds, axis=0)
    ratio = np.median(emp) / np.nanmedian(pred)
    # measured: empirical 0.122, predicted 0.137 (ratio 0.89); 8 realisations: the sample std is itself +-25 %
    assert 0.7 < ratio < 1.4, (np.median(emp), np.nanmedian(pred))
    exact = invert(sol.displacement, region=REGION, element_size=3.0, beta=1e-2)
    assert np.nanmedian(exact.uncertainty) < 0.5 * np.nanmedian(pred)


def test_unconstrained_elements_are_marked():
    """Elements without strain carry no information on mu: constrained False, uncertainty NaN."""
    def field(p):
        x = np.asarray(p, float)[:, 0]
        return np.column_stack([-0.01 * np.minimum(x - 15.0, 15.0), np.zeros(len(x))])

    res = invert(field, region=REGION, element_size=3.0, beta=1e-2)
    c = res.centroids[:, 0]
    assert not res.constrained[c > 33].any() and np.all(np.isnan(res.uncertainty[c > 33]))
    assert res.constrained[c < 27].all() and np.all(np.isfinite(res.uncertainty[c < 27]))


# ------------------------------------------------------------------------------------------------------------
# absolute stiffness, files, command line
# ------------------------------------------------------------------------------------------------------------
def test_reference_gives_kpa_and_round_trips(tmp_path):
    sol = solution("plane-stress", 40.0)
    ref_region = ((15.0, 21.0), (-15.0, 15.0))          # background band above the inclusion
    res = invert(sol.displacement, region=REGION, element_size=3.0, beta=1e-3, reference=(ref_region, 30.0))
    c = res.centroids
    sel = (c[:, 0] <= 21.0)
    assert abs(res.shear_modulus_kpa[sel].mean() - 10.0) < 1e-9      # equal areas: plain mean = E / 3
    assert np.allclose(res.youngs_modulus_kpa, 3 * res.shear_modulus_kpa)
    inside = inclusion(c)
    assert 3.2 < res.youngs_modulus_kpa[inside].mean() / 30.0 < 4.8   # the disk: ~4 x the reference
    back = load_inversion(res.save(tmp_path / "mu.npz"))
    assert np.array_equal(back.shear_modulus_kpa, res.shear_modulus_kpa)
    assert np.array_equal(back.uncertainty, res.uncertainty, equal_nan=True)
    assert np.array_equal(back.constrained, res.constrained)
    assert back.model_rule == res.model_rule and back.flags == res.flags
    for bad in ((ref_region, -1.0), ("x", 3.0), (((100.0, 110.0), (0.0, 1.0)), 30.0)):
        with pytest.raises(InputError):
            invert(sol.displacement, region=REGION, element_size=3.0, beta=1e-3, reference=bad)
    with pytest.raises(InputError, match="poisson"):
        invert(sol.displacement, region=REGION, poisson=0.49)


def _registration_file(tmp_path, model):
    from skfem import MeshQuad1

    sol = solution(model, 40.0)
    mesh = MeshQuad1.init_tensor(np.linspace(15, 45, 16), np.linspace(-15, 15, 16))
    v = sol.displacement(mesh.p.T)
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2], u[1::2] = v[:, 0], v[:, 1]
    path = tmp_path / f"{model}.npz"
    femreg.RegistrationResult(mesh, u, shape=(300, 100), spacing=(0.1, 0.3), origin=(15.0, -15.0)).save(path)
    return path


def test_cli_reference_auto_and_flagged_exit(tmp_path):
    from test_inversion import _cli

    pair = _registration_file(tmp_path, "plane-strain")
    r = _cli("invert", pair, "-o", tmp_path / "mu.npz", "--beta", "1e-3", "--reference", 15, 21, -15, 15, 30)
    assert r.returncode == 0, r.stderr
    res = load_inversion(tmp_path / "mu.npz")
    assert res.model == "plane-strain" and res.shear_modulus_kpa is not None and res.uncertainty is not None
    assert "kPa" in r.stdout
    # the plane-stress model on plane-strain data: flagged, exit 1, the result still written
    r = _cli("invert", pair, "-o", tmp_path / "f.npz", "--beta", "1e-3", "--model", "plane-stress")
    assert r.returncode == 1 and "strain ratio" in r.stderr and (tmp_path / "f.npz").exists()
    assert json.loads(str(np.load(tmp_path / "f.npz")["meta"]))["success"] is False
    r = _cli("invert", pair, "-o", tmp_path / "g.npz", "--reference", 15, 21, -15, 15, -3)
    assert r.returncode == 2 and "Traceback" not in r.stderr


# ------------------------------------------------------------------------------------------------------------
# the failing cases from registered RF pairs (slow: one registration each)
# ------------------------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("regularizer", ["momentum-stress", "momentum-strain", "strain"])
def test_registered_stiff_plane_strain_disk_is_right_or_flagged(regularizer):
    """A disk 4 x stiffer, plane strain, 1 %, 7 MHz probe: every default inversion is within 15 % or flagged,
    and none is on the wrong side of 1 unflagged."""
    from forward import fields as F
    from forward.pairs import make_pair

    f = F.Inclusion("stiff", "plane-strain", 0.01)
    pair = make_pair(f, "L7", (30, 30), 30, 0, top_mm=5.0)
    reg = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin, regularizer=regularizer)
    inside = lambda p: ((np.asarray(p)[:, 0] - 20) ** 2 + np.asarray(p)[:, 1] ** 2) < 25  # noqa: E731
    for model in ("auto", "plane-stress", "plane-strain"):
        res = invert(reg, model=model)
        c = modulus_contrast(res, inside)["contrast"]
        if res.success:
            assert c > 1 and abs(c / 4 - 1) <= 0.15, (model, c, res)


@pytest.mark.parametrize("boundary", ["axial-sides", "free-sides"])
def test_alternative_boundary_conditions_are_worse_on_exact_data(boundary, monkeypatch):
    """The image's lateral sides lie inside tissue: treating them as traction-free (in y, or in both components)
    is a model error, which the exact plane-stress field exposes; the measured-displacement default is closer."""
    from femreg import inversion

    # the boundary conditions, without the region refit (exact data at a small beta: 4.22 with the refit,
    # test_inversion_refit.py bounds it)
    monkeypatch.setattr(inversion, "TV_REFIT", None)
    sol = solution("plane-stress", 40.0)
    kw = dict(region=REGION, element_size=1.5, beta=3e-4, uncertainty=False)
    alt = modulus_contrast(invert(sol.displacement, boundary=boundary, **kw), inclusion)["contrast"]
    ref = modulus_contrast(invert(sol.displacement, **kw), inclusion)["contrast"]
    # measured: 4.09 with the measured sides, 2.6 with axial-only or free sides (true 4)
    assert abs(ref / 4 - 1) < 0.05 and abs(alt / 4 - 1) > 2 * abs(ref / 4 - 1), (ref, alt)
    with pytest.raises(InputError, match="boundary"):
        invert(sol.displacement, region=REGION, boundary="neumann")


# ------------------------------------------------------------------------------------------------------------
# one-step inversion from the images
# ------------------------------------------------------------------------------------------------------------
def _exact_pair_result():
    """A simulated RF pair of the stiff plane-strain disk (x4, 1 %) and a RegistrationResult holding the exact
    displacement on a 1.5 mm mesh over the imaged area."""
    from skfem import MeshQuad1

    from forward import fields as F
    from forward.pairs import make_pair

    f = F.Inclusion("stiff", "plane-strain", 0.01)
    pair = make_pair(f, "L7", (20.0, 20.0), 30, 0, top_mm=10.0)
    (x0, y0), n = pair.origin, pair.ref.shape
    x1, y1 = x0 + (n[0] - 1) * pair.spacing[0], y0 + (n[1] - 1) * pair.spacing[1]
    mesh = MeshQuad1.init_tensor(np.linspace(x0, x1, 14), np.linspace(y0, y1, 14))
    v = f.displacement(mesh.p.T)
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2], u[1::2] = v[:, 0], v[:, 1]
    rr = femreg.RegistrationResult(mesh, u, shape=pair.ref.shape, spacing=pair.spacing, origin=pair.origin)
    return f, pair, rr


def test_one_step_lowers_the_image_term_and_keeps_the_contrast():
    f, pair, rr = _exact_pair_result()
    inside = lambda p: f.inside(np.asarray(p))  # noqa: E731
    two = invert(rr, beta=0.01, uncertainty=False)
    one = invert(rr, beta=0.01, uncertainty=False, reference_image=pair.ref, moving_image=pair.mov)
    s = one.one_step
    assert s["psi_one_step"] < s["psi_two_step"] and s["nit"] >= 1
    c1, c2 = (modulus_contrast(r, inside)["contrast"] for r in (one, two))
    # measured: two-step 3.93, one-step 4.30 on 1.5 mm elements (truth 4); the band is 15 % either side
    assert abs(c1 / 4 - 1) < 0.15 and abs(c2 / 4 - 1) < 0.15, (c1, c2)
    for kw, word in ((dict(reference_image=pair.ref), "both"),
                     (dict(reference_image=pair.ref, moving_image=pair.mov[:-1]), "match")):
        with pytest.raises(InputError, match=word):
            invert(rr, beta=0.01, **kw)
    with pytest.raises(InputError, match="RegistrationResult"):
        invert(f.displacement, region=REGION, reference_image=pair.ref, moving_image=pair.mov)


def test_cli_one_step_from_image_files(tmp_path):
    from test_inversion import _cli

    f, pair, rr = _exact_pair_result()
    rr.save(tmp_path / "pair.npz")
    np.save(tmp_path / "ref.npy", pair.ref)
    np.save(tmp_path / "mov.npy", pair.mov)
    sp = [str(v) for v in pair.spacing]
    r = _cli("invert", tmp_path / "pair.npz", "-o", tmp_path / "mu.npz", "--beta", "0.01", "--images",
             tmp_path / "ref.npy", tmp_path / "mov.npy", "--spacing", *sp)
    assert r.returncode == 0, r.stderr
    assert "one-step" in r.stdout
    back = load_inversion(tmp_path / "mu.npz")
    assert back.one_step["psi_one_step"] < back.one_step["psi_two_step"]
