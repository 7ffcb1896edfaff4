"""The image term of eq:IR and what it is built on: the eq:wfnew gradient against finite differences of the energy,
the assembled data Hessians against an explicit J^T W J, point location (tensor, moved-tensor, general) against
the general search, the compiled loops against scipy, and the banded-Cholesky linear solver against SuperLU."""
import numpy as np
import pytest
import scipy.sparse as sp
from scipy import ndimage
from skfem import Basis, ElementQuad1, MeshQuad1

from femreg import _kernels
from femreg.data_term import SSDTerm
from femreg.image import SplineImage, cubic_at_index
from femreg.mesh import roi_mesh
from femreg.pixels import PixelQuadrature, PointLocator, logical_grid
from femreg.regularizers import make_regularizer
from femreg.solver import SPDSolver
from femreg.synthetic import speckle_image

SP = (0.0192, 0.3)          # paper sampling, mm
SHIFT = 7                   # axial shift of the moving image, pixels
C = 0.3                     # intensity offset of the moving image

PATHS = [pytest.param(True, id="compiled"), pytest.param(False, id="scipy")]


@pytest.fixture(params=PATHS)
def compiled(request, monkeypatch):
    """Run a test with the numba loops and with the scipy/numpy twins (the former skipped without numba)."""
    if request.param and _kernels._numba is None:
        pytest.skip("numba not installed: the compiled loops are not used")
    monkeypatch.setattr(_kernels, "HAVE_NUMBA", request.param)
    return request.param


@pytest.fixture(scope="module")
def big():
    return speckle_image((420, 36), SP, np.random.default_rng(5))


def moved(mesh, amp=1.0):
    """``mesh`` moved by a smooth field like an accumulated S_k: 1 % compression, lateral expansion, a bump."""
    x, y = mesh.p
    ux = -0.01 * x + 0.02 * amp * np.sin(x / 1.7) * np.cos(y / 2.3)
    uy = 0.005 * (y - y.mean()) + 0.03 * amp * np.cos(x / 1.3)
    return MeshQuad1(mesh.p + np.vstack([ux, uy]), mesh.t)


def _pair_problem(big, offset, mesh=None):
    """I_2 = I_1 shifted SHIFT pixels axially plus C: at u = SHIFT * dx the warped I_2 equals I_1 + C at every
    pixel and grad I_2(x + S + u) = grad I_1(x + S), so eq:wfnew's fixed-gradient form IS the derivative of psi
    there, while the residual (C) is not zero."""
    ref = big[40:340]
    mov = big[40 - SHIFT:340 - SHIFT] + C
    I1, I2 = SplineImage(ref, SP), SplineImage(mov, SP)
    # margin 0.8 mm = 41 px axially: the prefilter's boundary effect (0.27^d) is nil at the quadrature pixels
    mesh = mesh or roi_mesh(ref.shape, SP, element_size=(1.2, 3.0), margin=(0.8, 0.6))
    quad = PixelQuadrature(mesh, ref.shape, SP, (0.0, 0.0))
    S = None
    if offset:
        p = quad.points
        S = np.column_stack([0.012 * np.sin(p[:, 0] / 1.1), 0.02 * np.cos(p[:, 1] / 2.0)])
    data = SSDTerm(quad, I1, I2, offset=S)
    u = np.zeros(2 * mesh.p.shape[1])
    u[0::2] = SHIFT * SP[0]
    return mesh, data, u


@pytest.mark.parametrize("offset", [False, True], ids=["S=0", "S!=0"])
def test_gradient_is_the_derivative_of_the_energy(big, offset, compiled):
    mesh, data, u = _pair_problem(big, offset)
    r = data.residual(u)
    assert np.abs(r - C).max() < 1e-9, np.abs(r - C).max()          # the construction holds (measured 4e-14)
    g = data.gradient(u)
    h = 3e-6                                                          # mm (1.6e-4 pixel axially)
    fd = np.empty_like(u)
    for k in range(u.size):
        e = np.zeros_like(u)
        e[k] = h
        fd[k] = (data.energy(u + e) - data.energy(u - e)) / (2 * h)
    scale = np.abs(fd).max()
    assert scale > 1e-3                                               # a real, non-zero gradient
    err = np.abs(g - fd).max() / scale
    # measured 1.2e-8 (S = 0: exact knot gradient; the FD truncation, 1.3e-7 at h = 1e-5) and 1.3e-7 (S != 0:
    # spline gradient by a 1e-3 px central difference); a wrong weight, shape function or component order is O(1)
    assert err < (5e-8 if not offset else 5e-7), err


@pytest.mark.parametrize("mesh_kind", ["tensor", "moved"])
def test_data_hessian_equals_explicit_JtWJ(big, mesh_kind, compiled):
    base = roi_mesh((300, 36), SP, element_size=(1.2, 3.0), margin=(0.8, 0.6))
    mesh = base if mesh_kind == "tensor" else moved(base, amp=0.5)
    _, data, _ = _pair_problem(big, offset=False, mesh=mesh)
    if mesh_kind == "tensor":
        assert data.quad.location.grid is not None                    # the separable assembly is the one tested
    H = data.hessian().toarray()
    # explicit: pixel -> node interpolation from scikit-fem's own probes, J[p, 2i + a] = N_i(x_p) g_a(x_p)
    Pk = Basis(mesh, ElementQuad1()).probes(data.quad.points.T).toarray()
    g = data.ref_gradient
    J = np.empty((Pk.shape[0], 2 * Pk.shape[1]))
    J[:, 0::2] = Pk * g[:, [0]]
    J[:, 1::2] = Pk * g[:, [1]]
    H_ref = J.T @ (data.w[:, None] * J)
    err = np.abs(H - H_ref).max() / np.abs(H_ref).max()
    assert err < 1e-12, err                                           # measured ~1e-15
    assert np.allclose(H, H.T, rtol=0, atol=1e-14 * np.abs(H).max())


def _compare_locations(a, b, pts, mesh, rng):
    assert np.array_equal(a.inside, b.inside), (a.inside.sum(), b.inside.sum())
    f = rng.standard_normal(mesh.p.shape[1])
    va, vb = np.sum(a.N * f[a.nodes], 1), np.sum(b.N * f[b.nodes], 1)
    ga, gb = np.einsum("nk,nkd->nd", f[a.nodes], a.dN), np.einsum("nk,nkd->nd", f[b.nodes], b.dN)
    assert np.abs(va - vb).max() < 1e-12, np.abs(va - vb).max()     # measured ~1e-15
    # gradients differ only for a point on an edge shared by two elements (none among random points)
    assert np.abs(ga - gb).max() < 1e-9 * np.abs(gb).max(), np.abs(ga - gb).max()


def _general(mesh):
    loc = PointLocator(mesh)
    loc.tensor, loc._logical = None, False
    return loc


def test_tensor_grid_location_matches_general_search():
    mesh = roi_mesh((150, 30), (0.05, 0.2), element_size=0.7, margin=0.2)
    xa = np.linspace(-0.2, 7.6, 97)              # beyond the mesh at both ends
    ya = np.linspace(-0.1, 6.0, 31)
    a = PointLocator(mesh).locate_grid(xa, ya)
    assert a.grid is not None and a._N is None   # separable description, per-point arrays not built yet
    X, Y = np.meshgrid(xa, ya, indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel()])
    b = _general(mesh).locate(pts)
    assert 0 < a.inside.sum() < len(pts)
    _compare_locations(a, b, pts, mesh, np.random.default_rng(1))


def test_moved_mesh_location_matches_general_search(compiled):
    base = roi_mesh((400, 40), SP, element_size=(1.0, 2.0), margin=(0.5, 0.9))
    mesh = moved(base)
    assert logical_grid(mesh) is not None
    rng = np.random.default_rng(3)
    lo, hi = mesh.p.min(1) - 0.2, mesh.p.max(1) + 0.2
    pts = rng.uniform(lo, hi, (4000, 2))          # some outside the moved boundary
    a = PointLocator(mesh)
    la = a.locate(pts)
    assert a._logical                             # the walk was used
    lb = _general(mesh).locate(pts)
    assert 0.5 * len(pts) < la.inside.sum() < len(pts)
    _compare_locations(la, lb, pts, mesh, rng)
    # pixel quadrature on the moved mesh: same pixels, same interpolation operator
    qa = PixelQuadrature(mesh, (400, 40), SP, (0.0, 0.0))
    qb = PixelQuadrature(mesh, (400, 40), SP, (0.0, 0.0), locator=_general(mesh))
    assert np.array_equal(qa.index, qb.index)
    f = rng.standard_normal(mesh.p.shape[1])
    assert np.abs(qa.P @ f - qb.P @ f).max() < 1e-12


def test_compiled_interpolation_matches_map_coordinates(big):
    if _kernels._numba is None:
        pytest.skip("numba not installed: the compiled loops are not used")
    img = SplineImage(big, SP)
    rng = np.random.default_rng(4)
    idx = np.vstack([rng.uniform(-1.0, big.shape[0], 20000), rng.uniform(-1.0, big.shape[1], 20000)])
    idx[:, :6] = [[-0.5, big.shape[0] - 0.5, -0.5 - 1e-9, 3.0, np.nan, 10.0], [0.0, 2.0, 1.0, -0.5, 1.0, np.nan]]
    got = cubic_at_index(img._padded, idx, big.shape)
    want = ndimage.map_coordinates(img._padded, idx + 2.0, order=3, prefilter=False, mode="constant")
    hi = np.array(big.shape)[:, None] - 0.5
    outside = ~np.all((idx >= -0.5) & (idx <= hi), axis=0)
    want[outside] = 0.0
    assert np.all(got[outside] == 0.0) and outside[[2, 4, 5]].all() and not outside[[0, 1, 3]].any()
    assert np.abs(got - want).max() < 1e-11 * np.abs(big).max(), np.abs(got - want).max()   # measured 1e-13


@pytest.mark.parametrize("mesh_kind", ["tensor", "moved"])
def test_compiled_data_term_matches_sparse_products(big, mesh_kind, monkeypatch):
    if _kernels._numba is None:
        pytest.skip("numba not installed: the compiled loops are not used")
    base = roi_mesh((300, 36), SP, element_size=(1.2, 3.0), margin=(0.8, 0.6))
    mesh = base if mesh_kind == "tensor" else moved(base, amp=0.5)
    _, data, u = _pair_problem(big, offset=True, mesh=mesh)
    u = u + 0.004 * np.random.default_rng(6).standard_normal(u.size)
    out = {}
    for flag in (True, False):
        monkeypatch.setattr(_kernels, "HAVE_NUMBA", flag)
        data._cache_u = None
        out[flag] = (data.warped_moving(u), data.gradient(u))
    (w1, g1), (w0, g0) = out[True], out[False]
    assert np.abs(w1 - w0).max() < 1e-11 * np.abs(w0).max(), np.abs(w1 - w0).max()
    assert np.abs(g1 - g0).max() < 1e-11 * np.abs(g0).max(), np.abs(g1 - g0).max()


def test_banded_cholesky_solves_like_superlu_and_reuses_its_ordering(big):
    mesh, data, u = _pair_problem(big, offset=False)
    reg = make_regularizer("momentum-stress")
    reg.setup(mesh)
    b = np.random.default_rng(7).standard_normal(u.size)
    chol, lu = SPDSolver("cholesky"), SPDSolver("splu")
    for k in range(3):                            # lagged diffusivity: new values, same pattern, each iteration
        H = (data.hessian() + reg.hessian(u * (1 + 0.3 * k))).tocsc()
        x1, x0 = chol.solve(H, b), lu.solve(H, b)
        assert chol.last_method == "cholesky"
        assert np.abs(x1 - x0).max() < 1e-9 * np.abs(x0).max(), np.abs(x1 - x0).max()
    assert chol.n_factorizations == 3
    # a singular (semi-definite) matrix: the shift keeps it solvable, or SuperLU takes over
    Hs = sp.csc_matrix(reg.hessian(u))
    x = SPDSolver("auto").solve(Hs, reg.hessian(u) @ b)
    assert np.all(np.isfinite(x))


def test_unstructured_numbering_is_not_taken_for_a_grid():
    """A mesh whose elements are numbered otherwise than init_tensor's is located by the general search."""
    base = moved(roi_mesh((200, 30), SP, element_size=(1.0, 2.0), margin=(0.5, 0.9)))
    perm = np.random.default_rng(8).permutation(base.t.shape[1])
    mesh = MeshQuad1(base.p, base.t[:, perm])
    assert logical_grid(base) is not None and logical_grid(mesh) is None
    pts = np.random.default_rng(9).uniform(mesh.p.min(1), mesh.p.max(1), (1000, 2))
    a, b = PointLocator(mesh), PointLocator(base)
    la, lb = a.locate(pts), b.locate(pts)
    assert a._logical is False and b._logical
    _compare_locations(la, lb, pts, mesh, np.random.default_rng(10))
