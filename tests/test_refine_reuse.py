"""What a registration with the default refinement computes once instead of again: the element strain operator of a
mesh (femreg.fields.element_strain_operator), the edge jumps of a solve (femreg.refine._jump_parts), the envelope
windows the check reads per element and per parent cell (femreg.repair._lag_windows), the band-filtered pair
(femreg.refine._band_filtered, real transforms against the complex ones it replaced), and the band ordering's
candidates compared in 32-bit indices (femreg.linsolve.BandedPattern) -- each against the form it replaced."""
import collections

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.ndimage import gaussian_filter, uniform_filter
from scipy.sparse.csgraph import reverse_cuthill_mckee

import femreg
import femreg.fields as fields
import femreg.refine as R
import femreg.repair as repair
from femreg.linsolve import BandedPattern
from femreg.mesh import roi_mesh


def _mesh():
    return roi_mesh((400, 100), (0.05, 0.2), (0.0, 0.0), element_size=(1.0, 2.0))


def test_the_strain_operator_is_built_once_per_mesh_and_again_when_it_moves():
    m = _mesh()
    op = fields.element_strain_operator(m)
    assert fields.element_strain_operator(m) is op
    with pytest.raises(ValueError):
        op.data[0] = 1.0                     # shared by every caller: read-only
    G, _ = fields.centre_gradient_operators(m)
    ref = sp.vstack([G["xx"], G["yy"], 0.5 * (G["xy"] + G["yx"])]).tocsr()
    assert (op != ref).nnz == 0
    m.p[0] *= 2.0                            # changed in place: looked at again
    op2 = fields.element_strain_operator(m)
    assert op2 is not op
    assert np.allclose(op2[:m.t.shape[1]].toarray(), 0.5 * op[:m.t.shape[1]].toarray())


def test_the_jumps_of_one_solve_are_computed_once(monkeypatch):
    m = _mesh()
    rng = np.random.default_rng(0)
    u = rng.standard_normal(2 * m.p.shape[1]) * 1e-3
    calls = collections.Counter()
    edge = R.edge_jumps

    def counted(*a, **k):
        calls["n"] += 1
        return edge(*a, **k)

    monkeypatch.setattr(R, "edge_jumps", counted)
    opts = R.DEEP_REFINEMENT
    first = R._jumps(m, u, opts)
    again = R._jumps(m, u.copy(), opts)              # equal values, another array: still the kept ones
    assert calls["n"] == 1 and all(a is b for a, b in zip(first[:4], again[:4])) and first[4] == again[4]
    # another cut of the same jumps: no new jumps, its own cut, the one of jump_cut
    low = R._jumps(m, u, R.Refinement(threshold=1.0))
    assert calls["n"] == 1 and low[4] < first[4]
    e = R._centre_strains(m, u)
    ja, jl = edge(m, u, e=e)
    assert low[4] == R.jump_cut([ja, jl], R.Refinement(threshold=1.0), R.strain_scale(m, u, e=e))
    assert np.array_equal(first[0], ja) and np.array_equal(first[1], jl)
    with pytest.raises(ValueError):
        first[0][0, 0] = 0.0                         # read-only: mark() copies before it zeroes beam lines
    R._jumps(m, 2.0 * u, opts)                       # another displacement: computed
    assert calls["n"] == 2


def test_a_default_registration_computes_each_solve_s_jumps_once(monkeypatch):
    # a soft plane-stress disk under 7.5 MHz, split by the finer pass: the marking at two cuts, the relaxed edges
    # before and after, the slips along the beam and the layer test read one solve's jumps; measured: 1 computation
    # of the edge jumps (7 before they were kept) and 2 strain-operator builds (10 before), bound at those counts
    pytest.importorskip("forward")
    from forward import fields as F
    from forward.pairs import make_pair

    d = make_pair(F.Inclusion("soft", "plane-stress", 0.02, radius_mm=4.0), "L7", (20, 20), 20, 6, top_mm=3.0)
    calls = collections.Counter()
    for mod, name in ((R, "edge_jumps"), (fields, "centre_gradient_operators")):
        f = getattr(mod, name)
        monkeypatch.setattr(mod, name, lambda *a, _f=f, _n=name, **k: (calls.update([_n]), _f(*a, **k))[1])
    # the check reads the hop gain's envelope windows per element and per parent cell: computed once, and each
    # reading equal to one computed afresh
    windows, lag = repair._lag_windows_of, repair.envelope_lag_ncc
    fresh = []

    def counted_windows(*a, **k):
        calls.update(["windows"])
        return windows(*a, **k)

    def checked_lag(data, *a, **k):
        got = lag(data, *a, **k)
        kept = data.__dict__.pop(repair._LAG_ATTR)
        fresh.append(np.array_equal(got, lag(data, *a, **k), equal_nan=True))
        setattr(data, repair._LAG_ATTR, kept)
        return got

    monkeypatch.setattr(repair, "_lag_windows_of", counted_windows)
    monkeypatch.setattr(repair, "envelope_lag_ncc", checked_lag)
    res = femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin)
    assert res.success and res.refinement.passes and res.mesh.t.shape[1] > 1000, res.message
    assert calls["edge_jumps"] == 1, calls
    assert calls["centre_gradient_operators"] <= 2, calls
    # 2 readings (elements, parent cells), each also computed afresh here: 1 + 2 computations (was 2 + 2)
    assert len(fresh) == 2 and all(fresh), fresh
    assert calls["windows"] == 3, calls


def _complex_band(a, b):
    """The band filter as it was written with complex transforms of the whole spectrum."""
    fa, fb = np.fft.fft2(a), np.fft.fft2(b)
    power = uniform_filter(np.abs(fa) ** 2 + np.abs(fb) ** 2, R.BAND_SMOOTH, mode="wrap")
    keep = power >= R.BAND_LEVEL * power.max()
    return np.real(np.fft.ifft2(fa * keep)).ravel(), np.real(np.fft.ifft2(fb * keep)).ravel()


@pytest.mark.parametrize("shape", [(200, 40), (201, 41), (64, 9), (9, 64)])
def test_the_band_filter_on_half_spectra_equals_the_complex_one(shape):
    # speckle-like frames (axially correlated noise) and a decorrelated partner; measured 2e-16 - 6e-16 of the
    # largest value, bound 1e-12
    rng = np.random.default_rng(1)
    a = gaussian_filter(rng.standard_normal(shape), (3.0, 1.0))
    b = a + 0.3 * gaussian_filter(rng.standard_normal(shape), (3.0, 1.0))
    for got, want in zip(R._band_filtered(a, b), _complex_band(a, b)):
        assert np.max(np.abs(got - want)) <= 1e-12 * np.max(np.abs(want))


def _reference_pattern(H, upper):
    """The candidate choice in 64-bit indices (as it was written): reverse Cuthill-McKee, then the given order."""
    n = H.shape[0]
    col = np.repeat(np.arange(n), np.diff(H.indptr))
    best = None
    for perm in (reverse_cuthill_mckee(sp.csr_matrix(H), symmetric_mode=True).astype(np.int64), np.arange(n)):
        iperm = np.empty(n, dtype=np.int64)
        iperm[perm] = np.arange(n)
        i, j = iperm[H.indices], iperm[col]
        bw = int(np.max(np.abs(i - j), initial=0))
        if best is None or bw < best[0]:
            best = (bw, perm, i, j)
    bw, perm, i, j = best
    return perm, (bw if upper else int(np.max(i - j, initial=0))), i, j


@pytest.mark.parametrize("upper", [False, True])
@pytest.mark.parametrize("shuffle", [False, True])
def test_the_band_ordering_in_32_bit_indices_is_the_64_bit_one(upper, shuffle):
    # a momentum-like Hessian of a tensor mesh (its strain operator's Gram matrix plus a diagonal), in the mesh's
    # numbering (the given order wins) and shuffled (reverse Cuthill-McKee wins)
    m = _mesh()
    K = fields.element_strain_operator(m)
    H = (K.T @ K + sp.identity(K.shape[1])).tocsc()
    if shuffle:
        p = np.random.default_rng(2).permutation(H.shape[0])
        H = sp.csc_matrix(H[p][:, p])
    H.sort_indices()
    pat = BandedPattern(H, upper=upper)
    perm, bw, i, j = _reference_pattern(H, upper)
    assert np.array_equal(pat.perm, perm) and pat.bandwidth == bw
    sel, flat = pat._scatter_of(i, j)
    assert np.array_equal(pat.sel, sel) and np.array_equal(pat.flat, flat)
