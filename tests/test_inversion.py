"""Shear-modulus inversion (femreg.inversion): adjoint gradient, recovery of the forward models' moduli, uniform
blocks, files, bad input, CLI.

Ground truth: forward.solve_elasticity (P2 triangles, 1 mm near the inclusion) -- a different discretisation
from the inversion's bilinear quads, so nothing here starts from the answer.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

import femreg
from femreg.errors import InputError
from femreg.inversion import (_Model, _Problem, _Regularizer, _tensor_mesh, invert, load_inversion,
                              modulus_contrast)

#: Forward-model settings of the tests: 1 mm P2 elements over the imaged part (coarse, a second or two per solve).
FE = dict(mesh_size_mm=1.0, refine_region_mm=(50.0, 20.0))
#: Inversion region around the 15 mm inclusion at 30 mm depth, and element size.
REGION = ((15.0, 45.0), (-15.0, 15.0))
H = 1.5


def inclusion(points):
    p = np.asarray(points, float)
    return (p[:, 0] - 30.0) ** 2 + p[:, 1] ** 2 < 7.5 ** 2


_SOLUTIONS = {}


def solution(model, E_inc):
    import forward

    key = (model, E_inc)
    if key not in _SOLUTIONS:
        # the disk cache shares a solve across test files and worker processes (a fresh checkout solves each once)
        _SOLUTIONS[key] = forward.solve_elasticity(model, inclusion_modulus=E_inc, background_modulus=10.0,
                                                   cache=True, **FE)
    return _SOLUTIONS[key]


# ------------------------------------------------------------------------------------------------------------
# dense linear algebra of the beta rule and the Laplace step
# ------------------------------------------------------------------------------------------------------------
def test_spd_inverse_matches_lu_inverse_and_falls_back():
    from femreg.inversion import _spd_inverse

    rng = np.random.default_rng(3)
    X = rng.standard_normal((300, 300))
    A = X @ X.T / 300 + 1e-3 * np.eye(300)
    C = _spd_inverse(A.copy())
    ref = np.linalg.inv(A)
    # measured 3e-14 relative (the std of the 2318-element paper pair moved by 2e-14); bound 1e-10
    assert np.max(np.abs(C - ref)) <= 1e-10 * np.max(np.abs(ref))
    assert np.array_equal(C, C.T)           # both triangles filled
    B = A - 2.0 * np.eye(300) * np.max(np.diag(A))      # indefinite: the LU inverse
    assert np.allclose(_spd_inverse(B), np.linalg.inv(B), rtol=0, atol=1e-12 * np.max(np.abs(np.linalg.inv(B))))


def test_data_hessian_by_blocks_equals_the_full_product():
    from femreg.inversion import _data_hessian, _sensitivity

    rng = np.random.default_rng(4)
    mesh = _tensor_mesh(0.0, 9.0, 0.0, 7.0, (1.0, 1.0))
    p = mesh.p
    d = np.empty(2 * p.shape[1])
    d[0::2] = -0.01 * p[0] + 0.001 * np.sin(p[1])
    d[1::2] = 0.005 * p[1]
    fem = _Model(mesh, 99.0, reduced_volumetric=True, weights=(1.0, 0.1))
    prob = _Problem(fem, _Regularizer(mesh, "tv", 1.0, fem.area), d, s2=fem.area * 1e-4)
    theta = 0.3 * rng.standard_normal(fem.n_el)     # 63 elements: 8 blocks of 8, the last one short
    mu = np.exp(theta)
    u, lu = fem.solve(mu, prob.dirichlet)
    S = _sensitivity(fem, mu, u, lu)
    full = S.T @ (fem.M[fem.I][:, fem.I] @ S) / prob.s2
    Hd = _data_hessian(fem, prob, theta)
    assert np.array_equal(Hd, Hd.T)
    # measured 4e-16 relative (rounding of the blocked products); bound 1e-12
    assert np.max(np.abs(Hd - full)) <= 1e-12 * np.max(np.abs(full))


# ------------------------------------------------------------------------------------------------------------
# adjoint gradient
# ------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("model,lam,reg", [("plane-stress", 2.0, "tv"), ("plane-strain", 99.0, "tv"),
                                           ("plane-stress", 2.0, "tikhonov")])
def test_adjoint_gradient_matches_finite_differences(model, lam, reg):
    rng = np.random.default_rng(0)
    mesh = _tensor_mesh(0.0, 10.0, 0.0, 8.0, (1.0, 1.0))
    p = mesh.p

    d = np.empty(2 * p.shape[1])   # a smooth non-affine field
    d[0::2] = -0.01 * p[0] + 0.002 * np.sin(p[1] / 3.0) * p[0] / 10
    d[1::2] = 0.005 * p[1] + 0.001 * np.cos(p[0] / 4.0)
    fem = _Model(mesh, lam, reduced_volumetric=(model == "plane-strain"), weights=(1.0, 0.1))
    prob = _Problem(fem, _Regularizer(mesh, reg, 1.0, fem.area), d, s2=fem.area * 1e-4)
    theta = 0.3 * rng.standard_normal(fem.n_el)
    beta = 0.01
    _, g, _, _, _ = prob.evaluate(theta, beta)
    for trial in range(3):
        v = rng.standard_normal(fem.n_el)
        eps = 1e-5
        Jp = prob.evaluate(theta + eps * v, beta)[0]
        Jm = prob.evaluate(theta - eps * v, beta)[0]
        fd = (Jp - Jm) / (2 * eps)
        ad = float(g @ v)
        rel = abs(fd - ad) / abs(ad)
        # measured: 5e-10 - 2e-8 (central differences, O(eps^2) truncation); the bound is 1e-6
        assert rel <= 1e-6, f"directional derivative: adjoint {ad:.12g}, FD {fd:.12g}, rel. error {rel:.2e}"


def test_stiffness_assembly_equals_direct_skfem_assembly():
    """K(mu) from the precomputed element matrices equals scikit-fem's assembly with mu as a coefficient."""
    from skfem import Basis, ElementQuad1, ElementVector, asm

    from forward import elasticity_form

    mesh = _tensor_mesh(0.0, 5.0, 0.0, 4.0, (1.0, 1.0))
    mu = np.exp(np.random.default_rng(1).standard_normal(mesh.t.shape[1]))
    fem = _Model(mesh, 2.0, reduced_volumetric=False, weights=(1.0, 1.0))
    basis = Basis(mesh, ElementVector(ElementQuad1()), intorder=2)
    nq = basis.X.shape[1]
    M = np.repeat(mu[:, None], nq, 1)
    K = asm(elasticity_form(), basis, mu=M, lam=2.0 * M)
    assert abs(fem.stiffness(mu) - K).max() < 1e-12 * abs(K).max()


# ------------------------------------------------------------------------------------------------------------
# recovery of the forward models' moduli (exact displacements)
# ------------------------------------------------------------------------------------------------------------
def _check_recovery(res, truth, *, tol=0.05):
    m = modulus_contrast(res, inclusion)
    assert res.success, res.message
    err = abs(m["contrast"] / truth - 1)
    assert err <= tol, f"contrast {m['contrast']:.4f} vs true {truth} ({100 * err:.1f} %), {res}"
    assert m["edge_error_mm"] <= m["element_size_mm"], f"inclusion edge off by {m['edge_error_mm']:.2f} mm"
    return m


def test_plane_stress_hard_inclusion_contrast_and_edge():
    sol = solution("plane-stress", 40.0)
    # beta = 1e-4: what the L-curve rule picks on exact data (test_beta_rule_... runs the rule)
    res = invert(sol.displacement, model="plane-stress", region=REGION, element_size=H, beta=1e-4)
    m = _check_recovery(res, 4.0)
    # measured: contrast 4.09 (+2.3 %), edge error 1.0 mm with 1.5 mm elements
    assert abs(np.median(res.mu) - 1) < 0.02   # normalisation: median over the region = 1
    assert res.history.shape[1] == 3 and len(res.history) == res.nit
    assert m["n_wrong"] < 0.05 * res.mesh.t.shape[1]


def test_plane_strain_hard_inclusion_contrast_and_edge():
    sol = solution("plane-strain", 40.0)
    # the reduced-integration (Q1-P0) plane-strain model converges more slowly with h than plane stress:
    # measured contrast 4.14 (+3.5 %) with 1 mm elements, 4.31 (+7.7 %) with 1.5 mm
    res = invert(sol.displacement, model="plane-strain", region=REGION, element_size=1.0, beta=3e-4)
    _check_recovery(res, 4.0)


@pytest.mark.slow
@pytest.mark.parametrize("model", ["plane-stress", "plane-strain"])
@pytest.mark.parametrize("E_inc,truth", [(5.0, 0.5), (20.0, 2.0)])
def test_soft_and_mild_inclusions(model, E_inc, truth):
    sol = solution(model, E_inc)
    res = invert(sol.displacement, model=model, region=REGION, element_size=1.0, beta=3e-4)
    _check_recovery(res, truth)


@pytest.mark.parametrize("model", ["plane-stress", "plane-strain"])
def test_homogeneous_block_gives_uniform_modulus(model):
    sol = solution(model, 10.0)
    res = invert(sol.displacement, model=model, region=REGION, element_size=H, beta=1e-4)
    cv = float(np.std(res.mu) / np.mean(res.mu))
    # measured: CV 0.1-0.3 %; the bound is 2 %
    assert res.success and cv <= 0.02, f"CV {100 * cv:.2f} %"


def test_soft_inclusion_plane_stress_fast():
    """SI in the default suite (the slow test covers both models and mHI)."""
    sol = solution("plane-stress", 5.0)
    res = invert(sol.displacement, model="plane-stress", region=REGION, element_size=2.0, beta=3e-4)
    _check_recovery(res, 0.5)


def test_beta_rule_prefers_larger_beta_on_noisy_data():
    """With noise in the data, the regulariser-growth rule chooses a larger beta than with exact data."""
    sol = solution("plane-stress", 40.0)
    rng = np.random.default_rng(3)
    mesh = _tensor_mesh(15.0, 45.0, -15.0, 15.0, (3.0, 3.0))
    noise = {tuple(np.round(x, 6)): rng.standard_normal(2) for x in mesh.p.T}

    def noisy(p):
        u = sol.displacement(p)
        return u + np.array([2e-3, 1e-2]) * np.array([noise[tuple(np.round(x, 6))] for x in p])

    grid = (0.1, 0.01, 1e-3)
    exact = invert(sol.displacement, region=REGION, element_size=3.0, beta_grid=grid, beta_method="growth")
    rough = invert(noisy, region=REGION, element_size=3.0, beta_grid=grid, beta_method="growth")
    # measured: exact data keep the smallest beta (1e-3), noisy data stop at a larger one
    assert exact.beta == 1e-3 and rough.beta > exact.beta, (exact.sweep, rough.sweep)
    assert "R-growth" in rough.beta_rule


# ------------------------------------------------------------------------------------------------------------
# inputs, result object, files
# ------------------------------------------------------------------------------------------------------------
def test_registration_result_input_and_coarser_mesh(monkeypatch):
    """A RegistrationResult is inverted on its own mesh, or resampled onto a coarser one."""
    from skfem import MeshQuad1

    # the input path, without the region refit (exact data at a small beta: the refit reads 4.27 on the 2 mm mesh,
    # test_inversion_refit.py bounds it)
    monkeypatch.setattr(femreg.inversion, "TV_REFIT", None)

    sol = solution("plane-stress", 40.0)
    mesh = MeshQuad1.init_tensor(np.linspace(15, 45, 31), np.linspace(-15, 15, 31))
    v = sol.displacement(mesh.p.T)
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2], u[1::2] = v[:, 0], v[:, 1]
    rr = femreg.RegistrationResult(mesh, u, shape=(10, 10), spacing=(0.1, 0.3), origin=(0.0, 0.0))
    own = invert(rr, beta=3e-4, maxiter=150)
    assert own.mesh is mesh
    coarse = invert(rr, element_size=2.0, beta=3e-4, maxiter=150)
    assert coarse.mesh.t.shape[1] == 15 * 15
    for r in (own, coarse):
        c = modulus_contrast(r, inclusion)["contrast"]
        assert abs(c / 4 - 1) < 0.06, c     # measured 4.10 (own 1 mm), 4.05 (2 mm)


def test_shear_modulus_sampling_and_nan_outside():
    sol = solution("plane-stress", 40.0)
    res = invert(sol.displacement, region=REGION, element_size=3.0, beta=1e-3)
    v = res.shear_modulus(np.array([[30.0, 0.0], [20.0, -12.0], [100.0, 0.0], [np.nan, 0.0]]))
    assert v.shape == (4,) and np.isnan(v[2]) and np.isnan(v[3])
    assert v[0] > 2.5 * v[1]
    assert np.allclose(res.shear_modulus(res.centroids), res.element_values)


def test_save_load_vtu_and_plot(tmp_path):
    import meshio

    sol = solution("plane-stress", 40.0)
    res = invert(sol.displacement, region=REGION, element_size=3.0, beta=1e-3)
    path = res.save(tmp_path / "mu.npz")
    back = load_inversion(path)
    assert np.array_equal(back.mu, res.mu) and np.array_equal(back.u_measured, res.u_measured)
    assert back.beta == res.beta and back.model == res.model and back.success == res.success
    assert np.array_equal(back.history, res.history)
    assert femreg.inversion.is_inversion_file(path)
    assert not femreg.inversion.is_inversion_file(tmp_path / "nope.npz")
    res.to_vtu(tmp_path / "mu.vtu")
    m = meshio.read(tmp_path / "mu.vtu")
    assert np.allclose(m.cell_data["shear_modulus"][0], res.mu)
    fig = res.plot(tmp_path / "mu.png")
    assert (tmp_path / "mu.png").stat().st_size > 10_000
    assert len(fig.axes) >= 2


def test_bad_input_raises_input_error():
    sol = solution("plane-stress", 40.0)
    f = sol.displacement
    cases = [
        (dict(displacement=f), "region"),                                    # callable without region
        (dict(displacement=f, region=((45, 15), (-15, 15))), "x0 < x1"),
        (dict(displacement=f, region=REGION, model="3d"), "model"),
        (dict(displacement=f, region=REGION, beta=-1.0), "beta"),
        (dict(displacement=f, region=REGION, element_size=0.0), "element_size"),
        (dict(displacement=f, region=((15, 200), (-15, 15))), "NaN"),        # beyond the forward model's block
        (dict(displacement=lambda p: np.zeros((len(p), 2)), region=REGION), "no deformation"),
        (dict(displacement=lambda p: np.zeros((3, 2)), region=REGION), "shape"),
        (dict(displacement=np.zeros(10), region=REGION), "callable"),
        (dict(displacement=f, region=REGION, regularization="l1"), "regularization"),
        (dict(displacement=f, region=REGION, weights=(1.0, -1.0)), "weights"),
    ]
    for kw, word in cases:
        with pytest.raises(InputError, match=word):
            invert(**kw)


def test_failed_optimisation_reports_it():
    sol = solution("plane-stress", 40.0)
    res = invert(sol.displacement, region=REGION, element_size=3.0, beta=1e-3, maxiter=2)
    assert not res.success and res.message and res.nit <= 2


# ------------------------------------------------------------------------------------------------------------
# command line
# ------------------------------------------------------------------------------------------------------------
class _Run:
    def __init__(self, returncode, stdout, stderr):
        self.returncode, self.stdout, self.stderr = returncode, stdout, stderr


def _cli(*args, cwd=None):
    """The ``femreg`` command in-process (argparse exits become return codes)."""
    import contextlib
    import io

    from femreg.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main([str(a) for a in args])
        except SystemExit as exc:
            rc = exc.code
    return _Run(rc, out.getvalue(), err.getvalue())


def test_cli_invert_and_plot(tmp_path):
    from skfem import MeshQuad1

    sol = solution("plane-stress", 40.0)
    mesh = MeshQuad1.init_tensor(np.linspace(15, 45, 16), np.linspace(-15, 15, 16))
    v = sol.displacement(mesh.p.T)
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2], u[1::2] = v[:, 0], v[:, 1]
    femreg.RegistrationResult(mesh, u, shape=(300, 100), spacing=(0.1, 0.3), origin=(15.0, -15.0)).save(
        tmp_path / "pair.npz")
    r = _cli("invert", tmp_path / "pair.npz", "-o", tmp_path / "mu.npz", "--beta", "1e-3", "--vtu",
             tmp_path / "mu.vtu", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    res = load_inversion(tmp_path / "mu.npz")
    assert 3.5 < modulus_contrast(res, inclusion)["contrast"] < 4.5
    assert (tmp_path / "mu.vtu").exists()
    r = _cli("plot", tmp_path / "mu.npz", "-o", tmp_path / "mu.png", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "mu.png").stat().st_size > 10_000
    # bad input: exit 2 and a one-line reason
    r = _cli("invert", tmp_path / "pair.npz", "-o", tmp_path / "x.npz", "--model", "3d", cwd=tmp_path)
    assert r.returncode == 2 and "--model 3d needs a volume's result" in r.stderr
    r = _cli("invert", tmp_path / "pair.npz", "-o", tmp_path / "x.npz", "--model", "2d", cwd=tmp_path)
    assert r.returncode == 2 and "invalid choice" in r.stderr
    r = _cli("invert", tmp_path / "pair.npz", "-o", tmp_path / "x.npz", "--region", 15, 45, -15, 15, -5, 5,
             cwd=tmp_path)
    assert r.returncode == 2 and "--region takes 4 numbers (X0 X1 Y0 Y1, mm) for a 2D result, got 6" in r.stderr
    r = _cli("invert", tmp_path / "pair.npz", "-o", tmp_path / "x.npz", "--beta", "-2", cwd=tmp_path)
    assert r.returncode == 2 and "beta" in r.stderr and "Traceback" not in r.stderr
    # a failed optimisation: exit 1, the result is still written
    r = _cli("invert", tmp_path / "pair.npz", "-o", tmp_path / "f.npz", "--beta", "1e-3", "--maxiter", "1",
             cwd=tmp_path)
    assert r.returncode == 1 and (tmp_path / "f.npz").exists()
    meta = json.loads(str(np.load(tmp_path / "f.npz")["meta"]))
    assert meta["success"] is False
