"""Sampling on points and grids (femreg.sampling), the typed separable grid location (femreg.pixels.GridLocation)
and the data term's outside mask, against independent references: an affine field (exact for bilinear
elements), point-by-point location, and the moving-image index computed by hand."""
import numpy as np
import pytest

from femreg import _kernels
from femreg.data_term import SSDTerm
from femreg.image import SplineImage
from femreg.mesh import roi_mesh
from femreg.pixels import GridLocation, PixelQuadrature, PointLocator
from femreg.result import RegistrationResult
from femreg.sampling import PixelGrid, sample_grid, sample_points

SHAPE, SP, ORIGIN = (120, 40), (0.05, 0.2), (1.0, -4.0)
A = np.array([[-0.01, 0.004], [0.003, 0.006]])          # grad u of the affine field, (x, y) rows
B = np.array([0.02, -0.05])


@pytest.fixture(params=[True, False], ids=["compiled", "numpy"])
def compiled(request, monkeypatch):
    if request.param and not _kernels.HAVE_NUMBA:
        pytest.skip("numba absent")
    monkeypatch.setattr(_kernels, "HAVE_NUMBA", request.param and _kernels.HAVE_NUMBA)
    return request.param


def _affine_result():
    mesh = roi_mesh(SHAPE, SP, ORIGIN, element_size=(0.7, 1.1), margin=(0.3, 0.5))
    v = mesh.p.T @ A.T + B
    u = np.empty(2 * len(v))
    u[0::2], u[1::2] = v[:, 0], v[:, 1]
    return RegistrationResult(mesh, u, shape=SHAPE, spacing=SP, origin=ORIGIN)


def test_grid_location_is_typed_and_reproduces_the_points():
    res = _affine_result()
    x, y = PixelGrid.of(SHAPE, SP, ORIGIN).axes()
    loc = res.locator.locate_grid(x, y)
    gr = loc.grid
    assert isinstance(gr, GridLocation) and gr.shape == (gr.nr, gr.nc) and len(gr.axes) == 2
    xs, ys, _ = res.locator.tensor
    # break + local coordinate x interval length gives back the sample coordinates inside
    assert np.allclose(xs[gr.i] + gr.X * gr.hx, x[gr.rows], atol=1e-12)
    assert np.allclose(ys[gr.j] + gr.Y * gr.hy, y[gr.cols], atol=1e-12)
    assert gr.nr * gr.nc == int(loc.inside.sum())


@pytest.mark.parametrize("strain", ["element", "recovered"])
def test_grid_and_point_sampling_agree_and_are_exact_on_an_affine_field(compiled, strain):
    res = _affine_result()
    grid = PixelGrid.of(SHAPE, SP, ORIGIN)
    ns = res.nodal_strain if strain == "recovered" else None
    g = sample_grid(res.u, res.locator, grid, strain, nodal_strain=ns)
    pts = grid.points()
    p = sample_points(res.u, PointLocator(res.mesh), pts, ("ux", "uy", "exx", "eyy", "exy"), nodal_strain=ns)
    inside = np.isfinite(p[:, 0])
    assert 0.5 < inside.mean() < 1.0                       # the margin leaves pixels outside the mesh
    for k, name in enumerate(("ux", "uy", "exx", "eyy", "exy")):
        gv = g[name].ravel()
        assert np.array_equal(np.isfinite(gv), inside), name
        assert np.allclose(gv[inside], p[inside, k], rtol=0, atol=1e-12), name
    truth_u = pts[inside] @ A.T + B
    assert np.allclose(p[inside, :2], truth_u, atol=1e-12)
    assert np.allclose(p[inside, 2:], [A[0, 0], A[1, 1], 0.5 * (A[0, 1] + A[1, 0])], atol=1e-12)


def test_outside_mask_matches_the_moving_image_index_by_hand(compiled):
    rng = np.random.default_rng(3)
    img = rng.standard_normal(SHAPE)
    I1, I2 = SplineImage(img, SP, ORIGIN), SplineImage(img, SP, ORIGIN)
    mesh = roi_mesh(SHAPE, SP, ORIGIN, element_size=(0.7, 1.1), margin=(0.3, 0.5))
    data = SSDTerm(PixelQuadrature(mesh, SHAPE, SP, ORIGIN), I1, I2)
    v = mesh.p.T @ np.array([[0.0, 0.0], [0.0, 0.08]]).T + np.array([0.613, 0.0])   # down 0.613 mm, sheared laterally
    u = np.empty(2 * len(v))
    u[0::2], u[1::2] = v[:, 0], v[:, 1]
    mask = data.outside_mask(u)
    pts = data.quad.points
    pos = (pts + pts @ np.array([[0.0, 0.0], [0.0, 0.08]]).T + np.array([0.613, 0.0]) - ORIGIN) / SP
    hi = np.array(SHAPE) - 2.0
    ref = np.any((pos < 1.0) | (pos > hi), axis=1)
    assert 0.05 < ref.mean() < 0.6, ref.mean()
    assert np.array_equal(mask, ref)
