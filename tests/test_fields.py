"""femreg.fields: the one evaluation of displacement and strain of a bilinear-quad field."""
import numpy as np
import pytest
from skfem import MeshQuad1

from femreg.errors import InputError
from femreg.fields import element_strains, sample, strain_components
from femreg.pixels import PointLocator


def _mesh(seed=0, n=(9, 6), L=(9.0, 6.0)):
    m = MeshQuad1.init_tensor(np.linspace(0, L[0], n[0] + 1), np.linspace(0, L[1], n[1] + 1))
    p = m.p.copy()
    inner = (p[0] > 1e-9) & (p[0] < L[0] - 1e-9) & (p[1] > 1e-9) & (p[1] < L[1] - 1e-9)
    p[:, inner] += 0.2 * np.random.default_rng(seed).uniform(-1, 1, (2, inner.sum()))
    return MeshQuad1(p, m.t)


def _nodal(mesh, fx, fy):
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2], u[1::2] = fx(*mesh.p), fy(*mesh.p)
    return u


def test_affine_field_is_exact_everywhere():
    mesh = _mesh()
    G = np.array([[0.01, -0.004], [0.007, -0.02]])
    u = _nodal(mesh, lambda x, y: G[0, 0] * x + G[0, 1] * y + 0.3, lambda x, y: G[1, 0] * x + G[1, 1] * y - 0.1)
    pts = np.random.default_rng(1).uniform([0.5, 0.5], [8.5, 5.5], (200, 2))
    loc = PointLocator(mesh).locate(pts)
    f = sample(u, loc)
    assert loc.inside.all()
    np.testing.assert_allclose(f["ux"], G[0] @ pts.T + 0.3, atol=1e-14)
    np.testing.assert_allclose(f["uy"], G[1] @ pts.T - 0.1, atol=1e-14)
    for k, v in zip(("exx", "eyy", "exy"), (G[0, 0], G[1, 1], 0.5 * (G[0, 1] + G[1, 0]))):
        np.testing.assert_allclose(f[k], v, atol=1e-14)
    np.testing.assert_allclose(element_strains(mesh.p, mesh.t, u), [[G[0, 0], G[1, 1], 0.0015]] * mesh.t.shape[1],
                               atol=1e-14)


def test_strain_is_the_derivative_of_the_sampled_displacement():
    """Central differences of the sampled u inside elements reproduce the sampled strain (a random field)."""
    mesh = _mesh(seed=2)
    u = np.random.default_rng(3).standard_normal(2 * mesh.p.shape[1])
    loc0 = PointLocator(mesh)
    centres = mesh.p[:, mesh.t].mean(axis=1).T                    # well inside each quad
    h = 1e-6
    f = sample(u, loc0.locate(centres))
    ex = [sample(u, loc0.locate(centres + s * np.array([h, 0.0]))) for s in (1, -1)]
    ey = [sample(u, loc0.locate(centres + s * np.array([0.0, h]))) for s in (1, -1)]
    dux_dx, duy_dx = ((ex[0][c] - ex[1][c]) / (2 * h) for c in ("ux", "uy"))
    dux_dy, duy_dy = ((ey[0][c] - ey[1][c]) / (2 * h) for c in ("ux", "uy"))
    scale = np.abs(f["exx"]).max()
    np.testing.assert_allclose(f["exx"], dux_dx, atol=1e-7 * scale)
    np.testing.assert_allclose(f["eyy"], duy_dy, atol=1e-7 * scale)
    np.testing.assert_allclose(f["exy"], 0.5 * (dux_dy + duy_dx), atol=1e-7 * scale)


def test_element_strains_equal_sampled_strain_at_the_reference_centre():
    mesh = _mesh(seed=4)
    u = np.random.default_rng(5).standard_normal(2 * mesh.p.shape[1])
    # the image of the reference centre (1/2, 1/2) is the mean of the four corners (bilinear map)
    centres = mesh.p[:, mesh.t].mean(axis=1).T
    f = sample(u, PointLocator(mesh).locate(centres))
    e = element_strains(mesh.p, mesh.t, u)
    np.testing.assert_allclose(e, np.column_stack([f["exx"], f["eyy"], f["exy"]]), rtol=1e-10, atol=1e-12)
    assert strain_components(np.zeros((2, 2, 3, 4))).shape == (3, 4, 3)


def test_degenerate_quad_is_an_input_error():
    p = np.array([[0.0, 1.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    with pytest.raises(InputError, match="degenerate"):
        element_strains(p, np.arange(4).reshape(4, 1), np.zeros(8))


def test_grid_strains_agree_with_point_strains_both_modes():
    """The pixel-grid fields (compiled separable path) and ``strain(points)`` (general point location) give the
    same recovered and element strains."""
    import femreg
    from femreg.synthetic import speckle_pair

    spacing = (0.02, 0.1)
    ref, mov = speckle_pair(lambda p: np.c_[-0.01 * p[:, 0] + 0.002 * p[:, 1] ** 2, 0.004 * p[:, 1]],
                            shape=(300, 60), spacing=spacing, seed=2)
    res = femreg.register(ref, mov, spacing=spacing, element_size=(1.0, 1.0), maxiter=3)
    pts = res.pixel_points()
    for mode in ("recovered", "element"):
        g = res.on_grid(mode)
        e = res.strain(pts, mode)
        ok = np.isfinite(e[:, 0])
        assert ok.mean() > 0.3                      # the mesh inside the margins (measured 0.44)
        for k, name in enumerate(("exx", "eyy", "exy")):
            np.testing.assert_allclose(g[name].ravel()[ok], e[ok, k], atol=1e-12, rtol=0)
    assert np.nanmax(np.abs(res.on_grid()["exx"] - res.on_grid("element")["exx"])) > 1e-5   # they differ
