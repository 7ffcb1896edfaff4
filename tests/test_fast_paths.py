"""The fast paths of register's stages against their plain forms: compiled loops (femreg._kernels) against their
numpy twins, separable tensor-mesh evaluations against the per-point ones, the zero-padded analytic signal
against scipy.signal.hilbert."""
import numpy as np
import pytest

import femreg
from femreg import _kernels, pyramid
from femreg.fields import sample
from femreg.image import SplineImage, normalize_pair, pixel_axes
from femreg.mesh import roi_mesh
from femreg.repair import element_ncc
from femreg.synthetic import speckle_pair

SP = (0.025, 0.2)
SHAPE = (600, 80)                      # 15 x 16 mm

needs_numba = pytest.mark.skipif(_kernels._numba is None, reason="numba not installed: no compiled loops")


def compression(e):
    return lambda p: np.column_stack([-e * p[:, 0], 0.5 * e * (p[:, 1] - 8.0)])


@pytest.fixture(scope="module")
def pair():
    return speckle_pair(compression(0.02), SHAPE, SP, seed=3, snr_db=30)


@pytest.fixture(scope="module")
def result(pair):
    ref, mov = pair
    return femreg.register(ref, mov, spacing=SP)


@needs_numba
def test_compiled_global_search_matches_numpy(pair, monkeypatch):
    ref, mov = normalize_pair(*pair)[:2]
    stats = pyramid.speckle_statistics(ref, SP)
    s = pyramid.default_settings(ref.shape, SP, stats)
    er, em = pyramid._decimated_envelopes(ref, mov, s.decimation, stats.envelope, s.lateral_decimation)
    sp_c = (s.decimation * SP[0], s.lateral_decimation * SP[1])
    out = {}
    for flag in (True, False):
        monkeypatch.setattr(_kernels, "HAVE_NUMBA", flag)
        out[flag] = pyramid.global_search(er, em, sp_c, (0.0, 0.0))
        pos = np.arange(er.shape[0]) * 1.013 - 2.5            # inside and beyond both ends
        out[flag] += (pyramid._axial_resample(em, pos),)
    (c1, n1, r1), (c0, n0, r0) = out[True], out[False]
    assert np.abs(c1 - c0).max() < 1e-12 and abs(n1 - n0) < 1e-12, (c1, c0, n1, n0)
    assert np.abs(r1 - r0).max() < 1e-12 * np.abs(r0).max()


@needs_numba
def test_compiled_element_ncc_matches_bincount(result, pair, monkeypatch):
    ref, mov = normalize_pair(*pair)[:2]
    term = femreg.registration.image_term(SplineImage(ref, SP), SplineImage(mov, SP), result.mesh, SHAPE,
                                          np.asarray(SP), np.zeros(2))
    n_el = result.mesh.t.shape[1]
    q = {}
    for flag in (True, False):
        monkeypatch.setattr(_kernels, "HAVE_NUMBA", flag)
        q[flag] = element_ncc(term, result.u, n_el)
    assert np.array_equal(np.isnan(q[True]), np.isnan(q[False]))
    assert np.nanmax(np.abs(q[True] - q[False])) < 1e-12


@needs_numba
def test_compiled_outside_mask_matches_numpy(pair, monkeypatch):
    ref, mov = normalize_pair(*pair)[:2]
    I1, I2 = SplineImage(ref, SP), SplineImage(mov, SP)
    mesh = roi_mesh(SHAPE, SP, element_size=(1.0, 1.6))
    u0 = np.zeros(2 * mesh.p.shape[1])
    u0[0::2] = 1.0037 + 0.05 * mesh.p[0]               # 1-1.75 mm axially, 3 mm laterally: rows and columns
    u0[1::2] = 3.0137                                  # of pixels leave the moving image (no ties at the edge)
    w = {}
    for flag in (True, False):
        monkeypatch.setattr(_kernels, "HAVE_NUMBA", flag)
        sol = femreg.gnsolve.solve(I1, I2, mesh, SHAPE, np.asarray(SP), np.zeros(2),
                                         lambda: femreg.regularizers.make_regularizer("momentum-stress"), u0,
                                         maxiter=0, mask_outside=True)
        w[flag] = sol.data.w
    assert 0 < np.count_nonzero(w[False] == 0) < w[False].size
    assert np.array_equal(w[True], w[False])


@pytest.mark.parametrize("compiled", [pytest.param(True, marks=needs_numba), False])
def test_separable_grid_fields_match_point_sampling(result, compiled, monkeypatch):
    monkeypatch.setattr(_kernels, "HAVE_NUMBA", compiled)
    x, y = pixel_axes(result.shape, result.spacing, result.origin)
    loc = result.locator.locate_grid(x, y)
    assert loc.grid is not None
    for mode, nodal in (("element", None), ("recovered", result.nodal_strain)):
        ref = sample(result.u, loc, nodal_strain=nodal)
        result._grid = result._grid_element = None
        g = result.on_grid(mode)
        for k, v in ref.items():
            got = g[k].ravel()[loc.inside]
            assert np.abs(got - v).max() <= 1e-11 * max(np.abs(v).max(), 1e-12), (mode, k)   # round-off: 1.1e-12
            assert np.all(np.isnan(g[k].ravel()[~loc.inside]))


def test_padded_envelope_matches_hilbert_away_from_the_ends(pair):
    from scipy.signal import hilbert

    img = np.asarray(pair[0][:597], float)             # 597 = 3 x 199 rows: padded to a fast FFT length
    env = pyramid.envelope(img)
    ref = np.abs(hilbert(img, axis=0))
    inner = slice(60, -60)                             # > 4 RF periods (~14 samples each) from either end
    rel = np.abs(env[inner] - ref[inner]).max() / ref.max()
    assert rel < 0.02, rel                             # measured 0.3 %


@needs_numba
@pytest.mark.parametrize("shape", [(3, 3), (7, 4), (120, 37)])
def test_compiled_spline_prefilter_is_scipys(shape):
    from scipy import ndimage

    from femreg.image import _CUBIC_POLE

    x = np.random.default_rng(shape[0]).standard_normal(shape)
    want = np.pad(ndimage.spline_filter(x, order=3, mode="mirror"), 2, mode="reflect")
    got = _kernels.spline_coefficients(x, _CUBIC_POLE)
    assert np.abs(got - want).max() <= 1e-14 * np.abs(want).max()     # measured: bit for bit


def test_lateral_envelope_decimation_follows_the_pulse_cell():
    # simulated speckle: envelope and pulse cells agree, 1.8 mm at 0.3 mm pitch -> every other line; in vivo
    # frames: envelope cell 2.4-3.2 mm (echo structure), pulse cell 0.4 mm at ~0.2 mm pitch -> every line
    speckle = pyramid.SpeckleStats(period=0.14, cell=np.array([0.35, 1.8]), pulse_cell=np.array([0.35, 1.8]))
    tissue = pyramid.SpeckleStats(period=0.2, cell=np.array([0.9, 2.8]), pulse_cell=np.array([0.22, 0.4]))
    assert pyramid.default_settings((2000, 100), (0.019, 0.3), speckle).lateral_decimation == 2
    assert pyramid.default_settings((2000, 128), (0.02, 0.2), tissue).lateral_decimation == 1


@needs_numba
def test_compiled_envelope_warp_matches_map_coordinates(monkeypatch):
    rng = np.random.default_rng(4)
    img = rng.standard_normal((90, 40))
    g = np.stack(np.meshgrid(np.linspace(-0.5, 0.7, 90), np.linspace(-0.3, 0.4, 40), indexing="ij"), -1)
    g[..., 0] += 0.01 * rng.standard_normal(g.shape[:2])            # points beyond every edge, and inside
    out = {}
    for flag in (True, False):
        monkeypatch.setattr(_kernels, "HAVE_NUMBA", flag)
        out[flag] = pyramid._warp(img, (0.05, 0.1), (0.0, 0.0), g)
    assert np.array_equal(out[True] == 0, out[False] == 0) and (out[False] == 0).any()
    assert np.abs(out[True] - out[False]).max() < 1e-12              # measured 3e-15


@needs_numba
@pytest.mark.parametrize("shape, q, axis", [((300, 60), 2, 1), ((301, 40), 5, 0), ((7, 5), 6, 0), ((9, 3), 4, 1)])
def test_compiled_decimating_gaussian_matches_scipy(shape, q, axis):
    from scipy import ndimage

    e = np.random.default_rng(q).random(shape)
    want = ndimage.gaussian_filter1d(e, 0.5 * q, axis=axis)[(slice(None),) * axis + (slice(None, None, q),)]
    got = pyramid.gaussian_decimate(e, q, axis)                   # short axes: the reflection folds twice
    assert got.shape == want.shape and np.abs(got - want).max() < 1e-14   # measured 4e-16


@needs_numba
def test_compiled_envelope_lags_match_numpy(result, pair, monkeypatch):
    from femreg.repair import envelope_lag_ncc

    ref, mov = normalize_pair(*pair)[:2]
    term = femreg.registration.image_term(SplineImage(ref, SP), SplineImage(mov, SP), result.mesh, SHAPE,
                                          np.asarray(SP), np.zeros(2))
    period = femreg.pyramid.rf_period(ref, SP)
    c = {}
    for flag in (True, False):
        monkeypatch.setattr(_kernels, "HAVE_NUMBA", flag)
        c[flag] = envelope_lag_ncc(term, result.u, result.mesh.t.shape[1], period, SHAPE, SP)
    assert np.isfinite(c[True]).mean() > 0.5                  # most elements hold enough envelope samples
    assert np.array_equal(np.isnan(c[True]), np.isnan(c[False]))
    assert np.nanmax(np.abs(c[True] - c[False])) < 1e-12


@needs_numba
def test_compiled_knot_gradient_is_the_numpy_one(monkeypatch):
    rng = np.random.default_rng(5)
    img = SplineImage(rng.standard_normal((90, 40)), (0.02, 0.3), (1.0, -2.0))
    for block in [(slice(0, 90), slice(0, 40)), (slice(7, 61), slice(3, 38)), (slice(89, 90), slice(0, 1))]:
        g = {}
        for flag in (True, False):
            monkeypatch.setattr(_kernels, "HAVE_NUMBA", flag)
            g[flag] = img.gradient_at_pixels(block)
        assert all(np.array_equal(a, b) for a, b in zip(g[True], g[False]))
    # and the derivative of the interpolant itself (central difference of the spline, ~1e-7 relative)
    x, y = pixel_axes((90, 40), (0.02, 0.3), (1.0, -2.0))
    X, Y = np.meshgrid(x[7:61], y[3:38], indexing="ij")
    fd = img.gradient(np.column_stack([X.ravel(), Y.ravel()]))
    monkeypatch.setattr(_kernels, "HAVE_NUMBA", True)
    gx, gy = img.gradient_at_pixels((slice(7, 61), slice(3, 38)))
    scale = np.abs(fd).max(axis=0)
    assert np.abs(gx.ravel() - fd[:, 0]).max() < 1e-5 * scale[0]
    assert np.abs(gy.ravel() - fd[:, 1]).max() < 1e-5 * scale[1]


@needs_numba
@pytest.mark.parametrize("name", ["momentum-stress", "momentum-strain"])
def test_fixed_pattern_hessian_is_the_sparse_product(name, result, monkeypatch):
    import scipy.sparse as sp

    from femreg.regularizers import make_regularizer

    mesh = result.mesh
    reg = make_regularizer(name, alpha=0.3, hourglass=1.0)
    reg.setup(mesh)
    rng = np.random.default_rng(2)
    n = 2 * mesh.p.shape[1]
    C = reg.hessian(rng.standard_normal(n) * 1e-3) * 0.0
    C = C + sp.identity(n) * 5.0                 # a constant part (the data term's place) on the diagonal
    K, G = reg.operator.toarray(), reg.constant_hessian()
    for k, u in enumerate(rng.standard_normal((3, n)) * 1e-2):
        monkeypatch.setattr(_kernels, "HAVE_NUMBA", True)
        H = reg.hessian_plus(u, C)
        if k == 0:
            pattern = reg._gram
        assert reg._gram is pattern                 # the pattern is built once for the mesh, alpha and C
        d = np.tile(reg.diffusivity(u), 2)          # the x and y rows of each edge term
        dense = reg.alpha * (K.T * d) @ K + C.toarray() + (0 if G is None else reg.alpha * G.toarray())
        assert np.abs(H.toarray() - dense).max() < 1e-12 * np.abs(dense).max()
        monkeypatch.setattr(_kernels, "HAVE_NUMBA", False)
        assert np.abs(reg.hessian_plus(u, C).toarray() - dense).max() < 1e-12 * np.abs(dense).max()
    monkeypatch.setattr(_kernels, "HAVE_NUMBA", True)
    reg.alpha = 0.6                                  # a new alpha scales the constant part with it
    H2 = reg.hessian_plus(u, C).toarray()
    dense2 = 0.6 * (K.T * d) @ K + C.toarray() + (0 if G is None else 0.6 * G.toarray())
    assert np.abs(H2 - dense2).max() < 1e-12 * np.abs(dense2).max()
