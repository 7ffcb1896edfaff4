"""Exact speedups of the inversion: the blocked banded solve and the data Hessian equal their direct forms."""
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from femreg.linsolve import BLOCKED_SOLVE_MIN_RHS, SPDSolver


def _spd(nx, ny, seed=0):
    rng = np.random.default_rng(seed)
    a = sp.diags([-1, 2.5, -1], [-1, 0, 1], (nx, nx))
    b = sp.diags([-1, 2.5, -1], [-1, 0, 1], (ny, ny))
    A = sp.kron(a, sp.eye(ny)) + sp.kron(sp.eye(nx), b)
    A = sp.kron(A, np.array([[2.0, 0.5], [0.5, 1.5]])) + sp.diags(rng.uniform(0.1, 1.0, 2 * nx * ny))
    return A.tocsc(), rng


def test_blocked_banded_solve_equals_dpbtrs():
    """Many right-hand sides go through level-3 row blocks; the result is LAPACK dpbtrs's up to rounding, for both
    band storages and a last block shorter than the others."""
    for upper in (True, False):
        A, rng = _spd(23, 37)
        f = SPDSolver("cholesky", shift=0.0, upper=upper).factor(A)
        b = rng.normal(size=(A.shape[0], BLOCKED_SOLVE_MIN_RHS + 5))
        perm = f.pattern.perm
        ref = np.empty_like(b)
        ref[perm] = sla.cho_solve_banded((f.cb, not upper), b[perm], check_finite=False)
        x = f.solve(b)
        assert np.abs(x - ref).max() <= 1e-12 * np.abs(ref).max()
        assert np.abs(A @ x - b).max() < 1e-10


def test_data_hessian_equals_the_dense_product():
    """H_d = -B^T K^-1 (M S) / s^2 in column blocks equals S^T M S / s^2 with the dense S."""
    import femreg.inversion as I

    mesh = I._tensor_mesh(0.0, 12.0, -6.0, 6.0, (1.0, 1.0))
    fem = I._Model(mesh, 2.0, reduced_volumetric=False, weights=np.array([1.0, 0.3]))
    rng = np.random.default_rng(1)
    p = mesh.p
    d = np.empty(fem.basis.N)
    d[0::2], d[1::2] = -0.01 * p[0] + 1e-4 * rng.normal(size=p.shape[1]), 0.005 * p[1]
    reg = I._Regularizer(mesh, "tv", 1.0, fem.area)
    problem = I._Problem(fem, reg, d, 0.7)
    theta = 0.3 * rng.normal(size=fem.n_el)
    old = I.HESSIAN_COLUMNS
    try:
        I.HESSIAN_COLUMNS = 37           # several blocks, the last one short
        Hd = I._data_hessian(fem, problem, theta)
    finally:
        I.HESSIAN_COLUMNS = old
    mu = np.exp(theta)
    u, lu = fem.solve(mu, problem.dirichlet)
    S = I._sensitivity(fem, mu, u, lu)
    ref = S.T @ (fem.M[fem.I][:, fem.I] @ S) / problem.s2
    assert np.array_equal(Hd, Hd.T)
    assert np.abs(Hd - ref).max() <= 1e-10 * np.abs(ref).max()
