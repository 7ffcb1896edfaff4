"""forward.tissue.RandomTissue: the heterogeneous-tissue ground truth."""
import numpy as np
import pytest

from forward.tissue import RandomTissue

SMALL = dict(corr_mm=1.5, size_mm=(20.0, 20.0))


def _points():
    x, y = np.meshgrid(np.arange(2.0, 18.0, 0.25), np.arange(-8.0, 8.0, 0.25), indexing="ij")
    return np.column_stack([x.ravel(), y.ravel()])


@pytest.mark.parametrize("model, lateral", [("plane-stress", 0.495), ("plane-strain", 0.495 / 0.505)])
def test_uniform_block_is_uniaxial_compression(model, lateral):
    # sigma 0: a uniform block compressed frictionlessly, e_yy = nu (plane stress) or nu / (1 - nu) (plane strain)
    t = RandomTissue(0, 0.01, model, sigma=0.0, **SMALL)
    e = t.strain(_points())
    assert np.allclose(e[:, 0], -0.01, atol=1e-9)
    assert np.allclose(e[:, 1], 0.01 * lateral, atol=1e-9)
    assert np.allclose(e[:, 2], 0.0, atol=1e-9)
    u = t.displacement(np.array([[0.0, 0.0], [10.0, 0.0]]))
    assert np.allclose(u, [[0.0, 0.0], [-0.1, 0.0]], atol=1e-9)   # the probe's frame: top at rest


@pytest.mark.parametrize("model, ratio", [("plane-stress", 0.5), ("plane-strain", 0.98)])
def test_soft_tissue_strains_more(model, ratio):
    # measured on seeds 0-2: corr(log|e_xx|, log E) -0.77 .. -0.86, mean e_xx -0.0096 .. -0.0102,
    # median e_yy / e_xx -0.49 .. -0.53 (plane stress), -0.98 (plane strain)
    t = RandomTissue(1, 0.01, model, sigma=0.5, **SMALL)
    p = _points()
    e, E = t.strain(p), t.modulus(p)
    assert np.corrcoef(np.log(np.abs(e[:, 0])), np.log(E))[0, 1] < -0.6
    assert abs(e[:, 0].mean() + 0.01) < 0.001
    assert abs(np.median(e[:, 1]) / np.median(e[:, 0]) + ratio) < 0.06
    assert 0.2 < np.percentile(E, 2.5) < np.median(E) < np.percentile(E, 97.5) < 5.0


def test_seeded_and_validated():
    a = RandomTissue(3, 0.01, sigma=0.5, **SMALL)
    b = RandomTissue(3, 0.01, sigma=0.5, **SMALL)
    c = RandomTissue(4, 0.01, sigma=0.5, **SMALL)
    p = _points()[::50]
    assert np.array_equal(a.strain(p), b.strain(p))
    assert not np.allclose(a.modulus(p), c.modulus(p))
    assert np.all(np.isnan(a.displacement(np.array([[-1.0, 0.0], [5.0, 30.0]]))))
    with pytest.raises(ValueError, match="model"):
        RandomTissue(0, 0.01, "3d")
    with pytest.raises(ValueError, match="level"):
        RandomTissue(0, 0.5)
    with pytest.raises(ValueError, match="too small"):
        RandomTissue(0, 0.01, corr_mm=10.0, size_mm=(20.0, 20.0))


def test_heterogeneous_benchmark_scores():
    # the benchmark's score: the truth itself scores corr 1, RMS 0, all within 15 %; a flat image corr NaN-free 0
    from types import SimpleNamespace

    from benchmarks.heterogeneous import _score, CASES
    from benchmarks.robustness import select_cases
    from skfem import MeshQuad

    t = RandomTissue(2, 0.01, sigma=0.5, **SMALL)
    m = MeshQuad.init_tensor(np.linspace(2, 18, 17), np.linspace(-8, 8, 17))
    c = m.p[:, m.t].mean(axis=1).T
    roi = ((2.0, 18.0), (-8.0, 8.0))
    s = _score(SimpleNamespace(p=m.p, t=m.t), 3.0 * t.modulus(c), np.full(len(c), 0.01), t, roi)
    assert s["corr"] > 0.999 and s["rms_log"] < 1e-9 and s["in_band"] == 1.0 and s["calibrated"] == 1.0
    off = _score(SimpleNamespace(p=m.p, t=m.t), t.modulus(c) ** -1.0, None, t, roi)
    assert off["corr"] < -0.999 and off["in_band"] < 0.5
    assert [c.name for c in select_cases(CASES, "L15")] == ["tissue0.7-pstrain1_L15"]
