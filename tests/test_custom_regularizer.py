"""User-defined regularisers: from a scikit-fem BilinearForm (a) and from a TV operator (b)."""
import numpy as np
import pytest
import scipy.sparse as sp
from skfem import BilinearForm, MeshQuad1
from skfem.helpers import ddot, sym_grad

import femreg.regularizers as R
from femreg.regularizers.strain import (CENTRE_RULE, StrainIncompressibleRegularizer, StrainRegularizer,
                                        divergence_form, strain_energy_form)


def mesh_jittered(seed=0, n=(7, 5)):
    m = MeshQuad1.init_tensor(np.linspace(0, 3.5, n[0] + 1), np.linspace(0, 2.5, n[1] + 1))
    p = m.p.copy()
    inner = (p[0] > 1e-9) & (p[0] < 3.5 - 1e-9) & (p[1] > 1e-9) & (p[1] < 2.5 - 1e-9)
    p[:, inner] += 0.1 * np.random.default_rng(seed).uniform(-1, 1, (2, inner.sum()))
    return MeshQuad1(p, m.t)


def nodal(mesh, fn):
    ux, uy = fn(mesh.p[0], mesh.p[1])
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2], u[1::2] = ux, uy
    return u


def test_user_form_reproduces_R_eps_exactly():
    """A user writing R_eps's weak form themselves gets R_eps, bit for bit."""
    @BilinearForm
    def my_strain(u, v, w):
        return ddot(sym_grad(u), sym_grad(v))

    mesh = mesh_jittered()
    mine = R.from_form(my_strain, alpha=2.0e-3, quadrature="gauss3")
    ref = StrainRegularizer(alpha=2.0e-3)
    mine.setup(mesh)
    ref.setup(mesh)
    diff = abs(mine.hessian() - ref.hessian()).max()
    assert diff == 0.0, f"Hessian differs from R_eps by {diff:.3e}"
    u = np.random.default_rng(1).standard_normal(2 * mesh.p.shape[1])
    assert mine.energy(u) == ref.energy(u)
    np.testing.assert_array_equal(mine.gradient(u), ref.gradient(u))
    # and through the registry, as femreg.register would resolve it
    assert R.make_regularizer(mine) is mine


def test_user_forms_reproduce_R_eps_i():
    mesh = mesh_jittered(seed=2)
    mine = R.from_forms([(strain_energy_form, 1.0, "gauss3"), (divergence_form, 100.0, "centre")], alpha=1e-3)
    ref = StrainIncompressibleRegularizer(alpha=1e-3)
    mine.setup(mesh)
    ref.setup(mesh)
    diff = abs(mine.hessian() - ref.hessian()).max() / abs(ref.hessian()).max()
    assert diff < 1e-14, f"R_eps_i rebuilt from forms differs by {diff:.2e}"


def test_form_quadrature_choice_matters_and_is_honoured():
    """Centre rule on sym grad u : sym grad u integrates a bilinear field's strain at the centre only:
    an hourglass mode (u_x = x y on one element) has zero energy there but not with 3x3 Gauss."""
    mesh = MeshQuad1.init_tensor(np.array([0.0, 1.0]), np.array([0.0, 1.0]))
    u = nodal(mesh, lambda x, y: ((x - 0.5) * (y - 0.5), 0 * x))
    centre = R.from_form(strain_energy_form, alpha=1.0, quadrature="centre")
    gauss = R.from_form(strain_energy_form, alpha=1.0, quadrature="gauss3")
    explicit = R.from_form(strain_energy_form, alpha=1.0, quadrature=CENTRE_RULE)
    for r in (centre, gauss, explicit):
        r.setup(mesh)
    assert abs(centre.energy(u)) < 1e-15 and abs(explicit.energy(u)) < 1e-15
    # exact: 1/2 ∫ (y-1/2)^2 + 2 ((x-1/2)/2)^2 = 1/2 (1/12 + 1/24) = 1/16
    assert abs(gauss.energy(u) - 1.0 / 16.0) < 1e-14, f"3x3 Gauss energy {gauss.energy(u)!r} vs 1/16"


def test_tv_operator_energy_gradient_hessian():
    """(b): TV of the shear strain built from centre_gradient_operators in three lines."""
    def shear_tv(mesh):
        G, area = R.centre_gradient_operators(mesh)
        return [0.5 * (G["xy"] + G["yx"])], area

    mesh = mesh_jittered(seed=3)
    reg = R.from_operator(shear_tv, alpha=0.4, delta=1e-6)
    reg.setup(mesh)
    # affine field: exact energy alpha * area * sqrt(exy^2 + delta)
    g = np.array([[0.01, 0.03], [-0.02, 0.005]])
    u = nodal(mesh, lambda x, y: (g[0, 0] * x + g[0, 1] * y, g[1, 0] * x + g[1, 1] * y))
    exy = 0.5 * (g[0, 1] + g[1, 0])
    expected = 0.4 * 3.5 * 2.5 * np.sqrt(exy ** 2 + 1e-6)
    assert abs(reg.energy(u) - expected) < 1e-13, f"energy {reg.energy(u)!r} vs exact {expected!r}"
    # FD gradient and PSD Hessian at a random state
    rng = np.random.default_rng(5)
    u = 1e-2 * rng.standard_normal(u.size)
    d = rng.standard_normal(u.size)
    t = 1e-8
    fd = (reg.energy(u + t * d) - reg.energy(u - t * d)) / (2 * t)
    rel = abs(fd - reg.gradient(u) @ d) / abs(fd)
    assert rel < 1e-7, f"FD gradient rel err {rel:.2e}"
    H = reg.hessian(u).toarray()
    assert np.abs(H - H.T).max() <= 1e-12 * np.abs(H).max()
    ev = np.linalg.eigvalsh(H)
    assert ev.min() >= -1e-10 * ev.max(), f"min eigenvalue {ev.min():.3e}"


def test_quadratic_penalty_route_equals_form_route():
    """Both routes agree: sum_e area_e * 1/2 |eps(centre)|^2 as a 'quadratic' operator penalty equals the
    centre-rule strain BilinearForm."""
    def strain_components(mesh):
        G, area = R.centre_gradient_operators(mesh)
        return [G["xx"], G["yy"], np.sqrt(2.0) * 0.5 * (G["xy"] + G["yx"])], area

    mesh = mesh_jittered(seed=4)
    op = R.from_operator(strain_components, alpha=0.8, penalty="quadratic")
    form = R.from_form(strain_energy_form, alpha=0.8, quadrature="centre")
    op.setup(mesh)
    form.setup(mesh)
    u = np.random.default_rng(6).standard_normal(2 * mesh.p.shape[1])
    assert abs(op.energy(u) - form.energy(u)) < 1e-12 * form.energy(u)
    np.testing.assert_allclose(op.gradient(u), form.gradient(u), rtol=1e-11, atol=1e-12)
    diff = abs(op.hessian(u) - form.hessian()).max() / abs(form.hessian()).max()
    assert diff < 1e-12, f"Hessians differ by {diff:.2e}"


def test_custom_penalty_pair():
    """A user penalty (phi, dphi): log(1 + s / c) (Cauchy-like), FD-checked."""
    c = 1e-4
    penalty = (lambda s: np.log1p(s / c), lambda s: 1.0 / (c + s))

    def lateral_strain(mesh):
        G, area = R.centre_gradient_operators(mesh)
        return G["yy"], area

    mesh = mesh_jittered(seed=7)
    reg = R.from_operator(lateral_strain, alpha=1.0, penalty=penalty)
    reg.setup(mesh)
    rng = np.random.default_rng(8)
    u, d = 1e-2 * rng.standard_normal(2 * mesh.p.shape[1]), rng.standard_normal(2 * mesh.p.shape[1])
    t = 1e-8
    fd = (reg.energy(u + t * d) - reg.energy(u - t * d)) / (2 * t)
    rel = abs(fd - reg.gradient(u) @ d) / abs(fd)
    assert rel < 1e-6, f"FD gradient rel err {rel:.2e}"


# An independent R_P_sigma / R_P_eps (eq:dmreg2): the edge-midpoint jumps of A = lambda_bar div(u) I + 2 sym grad u
# (eq:meq) dotted with the side-0 normal, from scikit-fem's interpolation on both sides of every interior edge
# (and the element centres for R_P_eps's dilatation), and the lagged-diffusivity Hessian (eq:dmreg4) assembled by
# scikit-fem from helpers.jump -- none of femreg's operators or forms.
MIDPOINT = (np.array([[0.5]]), np.array([1.0]))          # 1-point rule on the reference edge [0, 1]
CENTRE = (np.array([[0.5], [0.5]]), np.array([1.0]))     # and on the reference square


def _A(g, lb, div=None):
    """A of a displacement gradient g (2, 2, ...); ``div`` replaces tr(g) in the dilatation part."""
    d = g[0, 0] + g[1, 1] if div is None else div
    return lb * d * np.eye(2).reshape(2, 2, *([1] * (g.ndim - 2))) + g + np.swapaxes(g, 0, 1)


class MomentumReference:
    def __init__(self, mesh, lambda_bar, alpha, delta, centre=False):
        from skfem import Basis, ElementQuad1, ElementVector, InteriorFacetBasis

        e = ElementVector(ElementQuad1())
        self.sides = [InteriorFacetBasis(mesh, e, side=s, quadrature=MIDPOINT) for s in (0, 1)]
        self.centres = Basis(mesh, e, quadrature=CENTRE) if centre else None
        self.lengths = self.sides[0].dx[:, 0]
        self.lb, self.alpha, self.delta = lambda_bar, alpha, delta

    def jumps(self, u):
        """[[A]] n per interior edge, (2, n_edges)."""
        n = self.sides[0].normals                          # both sides: the side-0 normal
        t = []
        for b in self.sides:
            div = None
            if self.centres is not None:
                gc = self.centres.interpolate(u).grad
                div = (gc[0, 0] + gc[1, 1])[b.tind]         # the dilatation of this side's element, at its centre
            t.append(np.einsum("ijfq,jfq->if", _A(b.interpolate(u).grad, self.lb, div), n))
        return t[0] - t[1]

    def energy(self, u):
        return self.alpha * float(self.lengths @ np.sqrt(np.sum(self.jumps(u) ** 2, axis=0) + self.delta))

    def hessian(self, u):
        """alpha K^T diag(l_j / sqrt(|K_j u|^2 + delta)) K as scikit-fem's assembly of jump(A[u] n) . jump(A[v] n)
        with the lagged coefficient (edge dilatation only)."""
        from skfem import BilinearForm, asm
        from skfem.helpers import dot, grad, jump

        @BilinearForm
        def lagged(u_, v_, w):
            ju, jv = jump(w, dot(_A(grad(u_), w.lb), w.n), dot(_A(grad(v_), w.lb), w.n))
            return w.c * dot(ju, jv)

        c = 1.0 / np.sqrt(np.sum(self.jumps(u) ** 2, axis=0) + self.delta)
        return self.alpha * asm(lagged, self.sides, self.sides, lb=self.lb, c=c[:, None])


def _meshes():
    return [mesh_jittered(seed=9), MeshQuad1.init_tensor(np.linspace(0, 3.0, 7), np.linspace(0, 2.4, 5) ** 1.2)]


@pytest.mark.parametrize("k", [0, 1], ids=["jittered", "tensor"])
def test_momentum_operator_through_the_public_route(k):
    """R_P_sigma rebuilt by a user with from_operator from an operator of their own (the jumps of every unit
    displacement, by scikit-fem's interpolation) equals the built-in; both match the independent Hessian."""
    mesh = _meshes()[k]
    builtin = R.make_regularizer("momentum-stress", alpha=1e-3)
    builtin.setup(mesh)
    ref = MomentumReference(mesh, builtin.lambda_bar, 1e-3, builtin.delta)
    n = 2 * mesh.p.shape[1]
    K = np.column_stack([ref.jumps(np.eye(n)[i]).ravel() for i in range(n)])       # (2 n_edges, n)
    m = K.shape[0] // 2

    def my_momentum(mesh_):
        return [sp.csr_matrix(K[:m]), sp.csr_matrix(K[m:])], ref.lengths

    mine = R.from_operator(my_momentum, alpha=1e-3)
    mine.setup(mesh)
    for seed in (10, 11):
        u = 1e-2 * np.random.default_rng(seed).standard_normal(n)
        E = ref.energy(u)
        assert abs(builtin.energy(u) - E) <= 1e-13 * E and abs(mine.energy(u) - E) <= 1e-13 * E
        H = ref.hessian(u).toarray()
        for reg in (builtin, mine):
            assert np.abs(reg.hessian(u).toarray() - H).max() <= 1e-12 * np.abs(H).max()
            g = reg.gradient(u)                                  # the lagged Hessian times u is the gradient
            assert np.abs(g - H @ u).max() <= 1e-12 * np.abs(g).max()


def test_user_can_register_a_name():
    @BilinearForm
    def axial_only(u, v, w):
        return sym_grad(u)[0, 0] * sym_grad(v)[0, 0]

    R.register_regularizer("test-axial-only", lambda alpha=None: R.from_form(axial_only, alpha=alpha or 1.0,
                                                                              name="test-axial-only"))
    try:
        reg = R.make_regularizer("test-axial-only", alpha=0.5)
        assert reg.name == "test-axial-only" and reg.alpha == 0.5
        mesh = mesh_jittered()
        reg.setup(mesh)
        u = nodal(mesh, lambda x, y: (0 * x, 0.01 * x + 0.02 * y))   # no axial strain
        assert abs(reg.energy(u)) < 1e-18
    finally:
        R.base._REGISTRY.pop("test-axial-only", None)


@pytest.mark.parametrize("bad", [
    lambda: R.from_form(lambda u, v, w: 0, alpha=1.0),
    lambda: R.from_form(strain_energy_form, alpha=1.0, quadrature="gauss7"),
    lambda: R.from_form(strain_energy_form, alpha=-1.0),
    lambda: R.from_forms([], alpha=1.0),
    lambda: R.from_forms([(strain_energy_form, -2.0, "gauss3")]),
    lambda: R.from_operator("not callable"),
    lambda: R.from_operator(lambda m: None, penalty="l0"),
    lambda: R.from_operator(lambda m: None, penalty=(np.sqrt,)),
    lambda: R.from_operator(lambda m: None, delta=0.0),
])
def test_bad_construction_raises(bad):
    with pytest.raises(ValueError):
        bad()


@pytest.mark.parametrize("operator", [
    lambda m: sp.eye(3, 2 * m.p.shape[1]),                                   # not a (components, weights) pair
    lambda m: ([sp.eye(3, 2 * m.p.shape[1])], np.ones(4)),                   # weights length
    lambda m: ([sp.eye(3, 7)], np.ones(3)),                                  # wrong number of columns
    lambda m: ([sp.eye(3, 2 * m.p.shape[1]), sp.eye(2, 2 * m.p.shape[1])], np.ones(3)),   # ragged
    lambda m: ([sp.eye(3, 2 * m.p.shape[1])], -np.ones(3)),                  # negative weights
])
def test_bad_operator_output_raises(operator):
    reg = R.from_operator(operator)
    with pytest.raises(ValueError):
        reg.setup(mesh_jittered())


def test_jump_form_tv_matches_side_by_side_interpolation_and_takes_data_through_w():
    """A user's TV weak form (jump of eps_yy across interior edges) equals the jump computed directly from
    scikit-fem's interpolation on both sides of every edge; a parameter in ``w`` scales it."""
    from skfem import ElementQuad1, ElementVector, InteriorFacetBasis, LinearForm

    from femreg.quadrature import EDGE_MIDPOINT_RULE

    @LinearForm
    def lateral_strain(v, w):
        return w.scale * sym_grad(v)[1, 1]

    mesh = mesh_jittered(seed=4)
    u = np.random.default_rng(5).standard_normal(2 * mesh.p.shape[1])
    reg = R.from_jump_forms([lateral_strain], alpha=1.0, scale=2.5)
    reg.setup(mesh)
    e = ElementVector(ElementQuad1())
    sides = [InteriorFacetBasis(mesh, e, side=s, quadrature=EDGE_MIDPOINT_RULE) for s in (0, 1)]
    expected = 2.5 * (sym_grad(sides[0].interpolate(u))[1, 1, :, 0] - sym_grad(sides[1].interpolate(u))[1, 1, :, 0])
    got = reg.term_values(u)[0]
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(reg.weights, sides[0].dx[:, 0], rtol=1e-14)
    affine = nodal(mesh, lambda x, y: (0.01 * x + 0.02 * y, -0.03 * x + 0.004 * y))
    assert np.abs(reg.term_values(affine)).max() < 1e-14


def test_momentum_regularizer_written_as_user_forms():
    """R_P_sigma written by a user from A[u] (eq:meq, inline) as two jump forms equals the independent reference
    (energy, gradient, lagged Hessian), as the built-in does."""
    from skfem import LinearForm
    from skfem.helpers import dot, sym_grad

    def A(v, lb):
        e = sym_grad(v)
        return lb * (e[0, 0] + e[1, 1]) * np.eye(2)[:, :, None, None] + 2.0 * e

    @LinearForm
    def tx(v, w):
        return dot(A(v, w.lb), w.n)[0]

    @LinearForm
    def ty(v, w):
        return dot(A(v, w.lb), w.n)[1]

    mesh = mesh_jittered(seed=6)
    u = 1e-2 * np.random.default_rng(1).standard_normal(2 * mesh.p.shape[1])
    builtin = R.PlaneStressMomentumRegularizer(alpha=0.7)
    builtin.setup(mesh)
    user = R.from_jump_forms([tx, ty], alpha=0.7, lb=2.0)
    user.setup(mesh)
    ref = MomentumReference(mesh, 2.0, 0.7, builtin.delta)
    E, H = ref.energy(u), ref.hessian(u).toarray()
    for reg in (user, builtin):
        assert abs(reg.energy(u) - E) <= 1e-13 * E
        assert np.abs(reg.hessian(u).toarray() - H).max() <= 1e-12 * np.abs(H).max()
        np.testing.assert_allclose(reg.gradient(u), H @ u, rtol=0, atol=1e-12 * np.abs(H @ u).max())


def test_centre_dilatation_momentum_matches_the_reference_and_finite_differences():
    """R_P_eps (dilatation at the element centre) against the reference with the centre divergence, and its
    gradient against central differences of the reference energy."""
    mesh = mesh_jittered(seed=6)
    reg = R.PlaneStrainMomentumRegularizer(alpha=0.7)
    reg.setup(mesh)
    assert reg.dilatation == "centre"
    ref = MomentumReference(mesh, reg.lambda_bar, 0.7, reg.delta, centre=True)
    rng = np.random.default_rng(1)
    u = 1e-2 * rng.standard_normal(2 * mesh.p.shape[1])
    E = ref.energy(u)
    assert abs(reg.energy(u) - E) <= 1e-13 * E
    assert abs(ref.energy(u) - MomentumReference(mesh, reg.lambda_bar, 0.7, reg.delta).energy(u)) > 1e-3 * E
    g = reg.gradient(u)
    for d in rng.standard_normal((3, u.size)):
        t = 1e-6
        fd = (ref.energy(u + t * d) - ref.energy(u - t * d)) / (2 * t)
        assert abs(fd - g @ d) <= 1e-6 * abs(fd), (fd, g @ d)


def test_user_data_reach_a_quadratic_form_through_w():
    """A depth-dependent weight passed as data: w.k (a number) scales the form, w.stiff (a nodal field) weights it
    pointwise; both equal the same weight written into the form."""
    @BilinearForm
    def weighted(u, v, w):
        return w.k * w.stiff[0] * ddot(sym_grad(u), sym_grad(v))

    @BilinearForm
    def written_in(u, v, w):
        return 3.0 * (1.0 + 0.1 * w.x[0]) * ddot(sym_grad(u), sym_grad(v))

    mesh = mesh_jittered(seed=7)
    stiff = nodal(mesh, lambda x, y: (1.0 + 0.1 * x, 0.0 * y))      # bilinear, so interpolation is exact
    a = R.from_form(weighted, alpha=1.0, k=3.0, stiff=stiff)
    b = R.from_form(written_in, alpha=1.0)
    a.setup(mesh)
    b.setup(mesh)
    err = abs(a.matrix - b.matrix).max() / abs(b.matrix).max()
    assert err < 1e-12, err


def test_centre_gradients_of_a_tensor_mesh_equal_scikit_fems(monkeypatch):
    """The tensor-mesh shortcut (one unit element, scaled per element) gives the Basis operators and areas."""
    import femreg.mesh as fm

    mesh = MeshQuad1.init_tensor(np.array([0.0, 0.3, 1.0, 1.2, 2.5]), np.array([-1.0, -0.2, 0.5, 0.9]))
    assert fm.tensor_structure(mesh) is not None
    G, area = R.centre_gradient_operators(mesh)
    monkeypatch.setattr(fm, "tensor_structure", lambda m: None)          # scikit-fem's Basis
    G0, area0 = R.centre_gradient_operators(mesh)
    for k in ("xx", "xy", "yx", "yy"):
        assert abs(G[k] - G0[k]).max() <= 1e-12 * abs(G0[k]).max(), k
    np.testing.assert_allclose(area, area0, rtol=1e-14)
    A = np.array([[0.3, -0.7], [0.2, 0.5]])                # an affine field: its gradient and divergence exactly
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2], u[1::2] = A @ mesh.p
    monkeypatch.undo()
    for k, (a, b) in {"xx": (0, 0), "xy": (0, 1), "yx": (1, 0), "yy": (1, 1)}.items():
        np.testing.assert_allclose(G[k] @ u, A[a, b], atol=1e-13)
    np.testing.assert_allclose(R.momentum.element_centre_divergence(mesh) @ u, 0.8, atol=1e-13)


def test_huber_keeps_a_step_that_the_quadratic_penalty_shrinks_in_proportion():
    """Denoising a step with R = alpha sum_j phi(|u_i - u_k|^2) over the mesh's axial node pairs: the Huber
    penalty (linear beyond sqrt(delta)) has a bounded influence, so each plateau moves by the same force
    alpha x (edges across the step) / (its nodes) whatever the step height (the TV solution: the terms across the
    step pull with alpha each, those inside a plateau cancel in its sum); the quadratic penalty's solution is
    linear in the data, so its shrinkage scales with the height."""
    from femreg.solver import Objective, gauss_newton

    mesh = MeshQuad1.init_tensor(np.linspace(0.0, 2.0, 21), np.array([0.0, 1.0]))
    n = mesh.p.shape[1]
    x, y = mesh.p
    order = np.lexsort((x, y))                            # nodes row by row, axially increasing
    pairs = np.array([(a, b) for a, b in zip(order[:-1], order[1:]) if y[a] == y[b]])
    rows = np.repeat(np.arange(len(pairs)), 2)
    K = sp.csr_matrix((np.tile([1.0, -1.0], len(pairs)), (rows, 2 * pairs.ravel())), shape=(len(pairs), 2 * n))

    class Fit:                                            # 0.5 |u - f|^2: the data of a denoising problem
        def __init__(self, f):
            self.f = f

        def energy(self, u):
            return 0.5 * float((u - self.f) @ (u - self.f))

        def gradient(self, u):
            return u - self.f

        def hessian(self, u=None):
            return sp.identity(u.size, format="csc")

    alpha = 0.05
    right = x > 1.0                                       # 20 nodes right, 22 left, 2 edges across the step
    shrink, spread = {}, {}
    for penalty in ("huber", "quadratic"):
        for h in (0.5, 5.0):
            f = np.zeros(2 * n)
            f[0::2][right] = h
            reg = R.from_operator(lambda m: ([K], np.ones(len(pairs))), alpha=alpha, penalty=penalty, delta=1e-12)
            reg.setup(mesh)
            gn = gauss_newton(Objective(Fit(f), reg), f, maxiter=200, tol=1e-12)
            ux = gn.x[0::2]
            shrink[penalty, h] = h - (ux[right].mean() - ux[~right].mean())
            spread[penalty, h] = np.ptp(ux[right]) / h      # how far the step leaks into its plateau
    # Huber: the plateaus move by 2 alpha / 20 and 2 alpha / 22, for either height
    for h in (0.5, 5.0):
        assert abs(shrink["huber", h] - 2 * alpha * (1 / 20 + 1 / 22)) < 1e-9, shrink
    # quadratic: linear in the data, the shrinkage is 10x for a 10x step
    assert abs(shrink["quadratic", 5.0] / shrink["quadratic", 0.5] - 10.0) < 1e-6, shrink
    # the Huber plateaus stay flat (to sqrt(delta) per node pair, relative to the step); the quadratic solution
    # smears the step into them by the same fraction for either height
    # (measured 9e-6 and 9e-7 of the step for Huber, 0.044 for the quadratic penalty)
    assert max(spread["huber", 0.5], spread["huber", 5.0]) < 1e-4, spread
    assert spread["quadratic", 0.5] > 0.01 and abs(spread["quadratic", 5.0] / spread["quadratic", 0.5] - 1) < 1e-6
