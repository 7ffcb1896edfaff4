"""The one linear-solver interface (femreg.linsolve) and the one lambda-bar (femreg.material), against dense
solves and Lame constants computed from Young's modulus and Poisson's ratio."""
import numpy as np
import pytest
import scipy.sparse as sp

from femreg.errors import InputError
from femreg.inversion import lambda_bar as inversion_lambda_bar
from femreg.linsolve import BandedPattern, SPDSolver
from femreg.material import lambda_bar
from femreg.regularizers import lambda_bar_from_poisson


def _spd(n_side=9, seed=0):
    """A 2D 5-point Laplacian plus a random positive diagonal, in a shuffled numbering (a band to find)."""
    T = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n_side, n_side))
    L = sp.kron(T, sp.identity(n_side)) + sp.kron(sp.identity(n_side), T)
    rng = np.random.default_rng(seed)
    A = (L + sp.diags(rng.uniform(0.1, 1.0, L.shape[0]))).tocsc()
    p = rng.permutation(A.shape[0])
    return sp.csc_matrix(A[p][:, p]), rng.standard_normal(A.shape[0])


@pytest.mark.parametrize("upper", [False, True])
def test_banded_pattern_solves_like_a_dense_solve(upper):
    A, b = _spd()
    pat = BandedPattern(A, upper=upper)
    assert pat.bandwidth < A.shape[0] // 3          # the shuffled numbering's band (~n) is reordered away
    x = pat.factor(A.data).solve(b)
    ref = np.linalg.solve(A.toarray(), b)
    assert np.abs(x - ref).max() < 1e-10 * np.abs(ref).max()


def test_every_method_agrees_and_an_indefinite_matrix_falls_back_to_superlu():
    A, b = _spd()
    ref = np.linalg.solve(A.toarray(), b)
    for method in ("auto", "cholesky", "splu", "spsolve"):
        x = SPDSolver(method, shift=0.0).solve(A, b)
        assert np.abs(x - ref).max() < 1e-10 * np.abs(ref).max(), method
    s = SPDSolver("cholesky", shift=0.0)
    f = s.factor(A)
    assert f.method == "cholesky" and s.factor(A).method == "cholesky"
    M = (A - 1.5 * sp.identity(A.shape[0])).tocsc()               # eigenvalues of both signs
    g = SPDSolver("cholesky", shift=0.0).factor(M)
    assert g.method == "splu"
    assert np.abs(M @ g.solve(b) - b).max() < 1e-9
    # a given ordering enters the competition: the identity on a banded matrix (RCM ties or loses)
    B = sp.diags([1.0, 4.0, 1.0], [-1, 0, 1], shape=(30, 30)).tocsc()
    assert BandedPattern(B, orderings=[np.arange(30)]).bandwidth == 1


@pytest.mark.parametrize("nu", [-0.5, 0.0, 0.3, 0.45, 0.495])
def test_lambda_bar_is_the_lame_ratio(nu):
    E = 3.7
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    assert lambda_bar("plane-strain", nu) == pytest.approx(lam / mu, rel=1e-13)
    lam_star = 2 * lam * mu / (lam + 2 * mu)                        # plane stress: the effective lambda
    assert lambda_bar("plane-stress", nu) == pytest.approx(lam_star / mu, rel=1e-13)
    assert lambda_bar_from_poisson(nu, "plane-strain") == lambda_bar("plane-strain", nu)
    assert inversion_lambda_bar("plane-strain", nu) == lambda_bar("plane-strain", nu)


def test_lambda_bar_has_one_range_and_one_error():
    assert lambda_bar("plane-stress", 0.5) == 2.0 and inversion_lambda_bar("plane-stress") == 2.0
    assert inversion_lambda_bar("plane-strain") == pytest.approx(2 * 0.495 / (1 - 2 * 0.495))
    for model, nu in (("plane-strain", 0.5), ("plane-strain", -1.0), ("plane-stress", 0.51), ("plane-stress", -1.0),
                      ("plane-strain", float("nan")), ("plane-strain", "x")):
        for fn in (lambda m, v: lambda_bar(m, v), lambda m, v: lambda_bar_from_poisson(v, m),
                   lambda m, v: inversion_lambda_bar(m, v)):
            with pytest.raises(InputError, match="poisson"):
                fn(model, nu)
    with pytest.raises(InputError, match="model"):
        lambda_bar("3d", 0.3)
    assert issubclass(InputError, ValueError)


@pytest.mark.parametrize("upper", [False, True])
def test_band_widths_in_column_blocks_equal_the_whole_pattern(upper, monkeypatch):
    import femreg.linsolve as LS

    A, _ = _spd(n_side=11, seed=3)
    whole = BandedPattern(A, upper=upper)
    # the band by brute force in the chosen order
    iperm = np.empty(A.shape[0], int)
    iperm[whole.perm] = np.arange(A.shape[0])
    C = A.tocoo()
    d = iperm[C.row] - iperm[C.col]
    assert whole.bandwidth == (np.abs(d).max() if upper else d.max())
    monkeypatch.setattr(LS, "BAND_CHUNK", 7)                    # a few entries per block
    small = BandedPattern(A, upper=upper)
    assert small.bandwidth == whole.bandwidth and np.array_equal(small.perm, whole.perm)
    assert np.array_equal(small.flat, whole.flat) and np.array_equal(small.sel, whole.sel)


def test_upper_triangle_for_pardiso_equals_scipy_triu():
    from femreg.linsolve import _upper_csr

    A, _ = _spd(n_side=8, seed=1)
    for shift in (0.0, 0.25):
        want = sp.triu(A + shift * sp.identity(A.shape[0]), format="csr")
        want.sort_indices()
        got = _upper_csr(A, shift)
        assert np.array_equal(got.indptr, want.indptr) and np.array_equal(got.indices, want.indices)
        assert np.array_equal(got.data, want.data)


def test_pardiso_factors_are_freed_before_the_next_and_by_release(monkeypatch):
    """MKL holds a PARDISO factor outside Python: every factor is freed before the next is made, and by
    ``release`` (a 3D Gauss-Newton solve used to keep one per iteration, 0.3 GB each on the paper phantom)."""
    pypardiso = pytest.importorskip("pypardiso")
    freed = []
    orig = pypardiso.PyPardisoSolver.free_memory
    monkeypatch.setattr(pypardiso.PyPardisoSolver, "free_memory",
                        lambda self, everything=False: (freed.append(everything), orig(self, everything))[1])
    A, b = _spd()
    ref = np.linalg.solve(A.toarray(), b)
    s = SPDSolver("pardiso", shift=0.0)
    for k in range(3):
        x = s.solve(A, b)           # a new factorisation each time (reuse False)
        assert np.abs(x - ref).max() < 1e-10 * np.abs(ref).max()
        assert s.last_method == "pardiso" and len(freed) == k      # the previous ones, not this one
    s.release()
    assert freed == [True] * 3 and s._fact is None
    s.release()                     # idempotent
    assert len(freed) == 3


@pytest.mark.parametrize("constant", [False, True])
def test_gauss_newton_keeps_a_factor_only_when_it_reuses_it(constant):
    """A Gauss-Newton step that factorises anew drops the matrix's factor before its line search (a volume's
    PARDISO factor is ~1 GB); a constant Hessian keeps its one factor for every step."""
    from femreg.solver import gauss_newton

    A, b = _spd()

    class Quadratic:
        hessian_constant = constant

        def energy(self, x):
            return 0.5 * x @ (A @ x) - b @ x + 0.1 * np.sum(x ** 4)

        def gradient(self, x):
            return A @ x - b + 0.4 * x ** 3

        def hessian(self, x):
            return sp.csc_matrix(A + sp.diags(1.2 * x ** 2)) if not constant else A

    s = SPDSolver("auto", shift=0.0)
    res = gauss_newton(Quadratic(), np.zeros(A.shape[0]), maxiter=6, tol=1e-12, linear_solver=s)
    assert res.nit >= 2
    assert (s._fact is not None) == constant
    assert s.n_factorizations == (1 if constant else res.nit)
