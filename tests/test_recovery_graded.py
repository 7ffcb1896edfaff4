"""Recovered strain on a graded tensor mesh (element sizes changing across rows and columns, as refinement leaves
them): the nodal average weighted by 1 / element area (femreg.fields.graded_weights) has no kink where the size
changes, the equal-weight one (femreg's recoveries) has; a true step keeps its width either way."""
import numpy as np
import pytest
from skfem import MeshQuad1

from femreg.errors import InputError
from femreg.fields import adaptive_strains, element_strains, graded_weights, nodal_average, recovered_strains
from femreg.pixels import PointLocator
from femreg.sampling import PixelGrid, sample_grid

# 1 mm elements with a band of 0.25 mm rows (x 4-8 mm) and of 0.5 mm columns (y 5-7 mm)
XS = np.unique(np.r_[np.arange(0.0, 4.0, 1.0), np.arange(4.0, 8.0, 0.25), np.arange(8.0, 12.01, 1.0)])
YS = np.unique(np.r_[np.arange(0.0, 5.0, 1.0), np.arange(5.0, 7.0, 0.5), np.arange(7.0, 12.01, 1.0)])
GRID = PixelGrid.of((91, 91), (0.1, 0.1), (1.5, 1.5))   # pixels 1.5-10.5 mm: off the boundary elements


def _mesh():
    return MeshQuad1.init_tensor(XS, YS)


def _staircase(img, truth):
    """RMS of the second differences of ``img - truth`` along x and along y, over the range of ``truth``."""
    d = img - truth
    span = np.ptp(truth)
    return (float(np.sqrt(np.mean(np.diff(d, 2, axis=0) ** 2))) / span,
            float(np.sqrt(np.mean(np.diff(d, 2, axis=1) ** 2))) / span)


def _linear_shear(m):
    """ux = a x y, uy = b x y: e_xy = (a x + b y) / 2, linear in both directions."""
    a, b = 0.004, 0.002
    u = np.zeros(2 * m.p.shape[1])
    u[0::2], u[1::2] = a * m.p[0] * m.p[1], b * m.p[0] * m.p[1]
    X, Y = np.meshgrid(*GRID.axes(), indexing="ij")
    return u, 0.5 * (a * X + b * Y)


def test_graded_average_has_no_kink_where_the_element_size_changes():
    m = _mesh()
    u, truth = _linear_shear(m)
    loc = PointLocator(m)
    e = element_strains(m.p, m.t, u)
    graded = nodal_average(m.t, e, m.p.shape[1], graded_weights(m.p, m.t))
    sx, sy = _staircase(sample_grid(u, loc, GRID, "recovered", nodal_strain=graded)["exy"], truth)
    # measured below 1e-15 of the strain range (rounding); bound 1e-9
    assert sx < 1e-9 and sy < 1e-9, (sx, sy)
    # the equal-weight average (femreg's "average" recovery, and the adaptive one at weight 0) kinks at every size
    # change
    for plain in (recovered_strains(m.p, m.t, u, "average"), adaptive_strains(m.p, m.t, u, 0.0)):
        sx, sy = _staircase(sample_grid(u, loc, GRID, "recovered", nodal_strain=plain)["exy"], truth)
    # measured 1.2e-3 (x) and 2.6e-4 (y) of the range: what the weights remove (bound a tenth of it)
        assert sx > 1.2e-4 and sy > 2.6e-5, (sx, sy)


def test_uniform_mesh_weights_are_the_plain_average():
    m = MeshQuad1.init_tensor(np.linspace(0, 6, 7), np.linspace(0, 4, 9))
    np.testing.assert_allclose(graded_weights(m.p, m.t), 1.0, rtol=1e-12)
    rng = np.random.default_rng(3)
    u = rng.normal(size=2 * m.p.shape[1]) * 1e-3
    e = element_strains(m.p, m.t, u)
    np.testing.assert_allclose(nodal_average(m.t, e, m.p.shape[1], graded_weights(m.p, m.t)),
                               recovered_strains(m.p, m.t, u, "average"), rtol=0, atol=1e-15)
    with pytest.raises(InputError, match="cell_weights"):
        nodal_average(m.t, e, m.p.shape[1], np.ones(3))


def _band(m, lo, hi, slide=0.1):
    """uy a ramp across x in [lo, hi] (a shear band of e_xy = slide / (2 (hi - lo)), zero outside)."""
    u = np.zeros(2 * m.p.shape[1])
    u[1::2] = slide * np.clip((m.p[0] - lo) / (hi - lo), 0.0, 1.0)
    return u, slide / (2 * (hi - lo))


def _rise(profile, x, peak):
    """10-90 % rise distance (mm) of an increasing ``profile`` on the axis ``x``."""
    return float(np.interp(0.9 * peak, profile, x) - np.interp(0.1 * peak, profile, x))


def test_a_band_face_stays_sharp():
    m = _mesh()
    loc = PointLocator(m)
    x = GRID.axes()[0]
    for lo, hi in ((5.0, 6.0), (4.0, 6.0)):          # faces inside the fine rows, and on the size change at 4 mm
        u, peak = _band(m, lo, hi)
        e = element_strains(m.p, m.t, u)
        rises = {}
        for name, ns in (("graded", nodal_average(m.t, e, m.p.shape[1], graded_weights(m.p, m.t))),
                         ("adaptive", adaptive_strains(m.p, m.t, u)),
                         ("plain", recovered_strains(m.p, m.t, u, "average"))):
            prof = sample_grid(u, loc, GRID, "recovered", nodal_strain=ns)["exy"][:, 45]
            face = (x >= lo - 1.5) & (x <= lo + 0.5)
            rises[name] = _rise(prof[face], x[face], peak)
            # the band's strain neither lost nor overshot (measured 1 to 2e-16)
            assert abs(np.nanmax(prof) / peak - 1.0) < 1e-9, name
        # measured 0.40 mm (face inside the 0.25 mm rows) and 1.00 mm (face on the change from 1 mm to
        # 0.25 mm rows) for every recovery: the weights widen the face by nothing (margin 0.01 mm)
        assert rises["graded"] <= rises["plain"] + 0.01 and rises["adaptive"] <= rises["plain"] + 0.01, rises
        assert rises["graded"] <= {5.0: 0.41, 4.0: 1.01}[lo], rises
