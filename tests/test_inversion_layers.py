"""Layers in series: the inversion's layer check (femreg.inversion._layer_contradiction) against true layered
tissue (forward.tissue.LayeredTissue) and against layers the data do not show."""
from __future__ import annotations

import numpy as np
import pytest
from skfem import MeshQuad

import femreg
from femreg.inversion import LAYER_CONTRAST, _layer_contradiction
from forward.tissue import LayeredTissue


def _grid(nx=20, ny=24):
    m = MeshQuad.init_tensor(np.linspace(0.0, 40.0, nx + 1), np.linspace(-24.0, 24.0, ny + 1))
    c = m.p[:, m.t].mean(axis=1)
    return m, c, np.full(m.t.shape[1], 4.0)


def test_layers_at_equal_strain_are_flagged():
    m, c, area = _grid()
    sel = np.ones(c.shape[1], bool)
    mu = np.where(c[0] < 28.0, 2.7, 1.0)
    same = np.full(mu.size, 0.023)
    why = _layer_contradiction(mu, same, m, sel, area)
    assert "2.7 x as stiff" in why and "above 28" in why, why
    # real layers in series: the stiffer strains less by about the modulus ratio (or at least a tenth of it in log)
    assert _layer_contradiction(mu, 0.023 / mu, m, sel, area) == ""
    assert _layer_contradiction(mu, 0.023 / mu ** 0.2, m, sel, area) == ""
    assert _layer_contradiction(mu, 0.023 * mu ** 0.1, m, sel, area) != ""         # the wrong way round
    # a step below the contrast, an inclusion narrower than half the image, a uniform image: nothing to test
    assert _layer_contradiction(np.where(c[0] < 28.0, 0.95 * LAYER_CONTRAST, 1.0), same, m, sel, area) == ""
    disk = np.where(np.hypot(c[0] - 20.0, c[1]) < 8.0, 4.0, 1.0)
    assert _layer_contradiction(disk, same, m, sel, area) == ""
    assert _layer_contradiction(np.ones(mu.size), same, m, sel, area) == ""
    # a thin stiff layer under the probe (15 % of the depth): at equal strain as contradictory, in series not
    thin = np.where(c[0] < 6.0, 3.0, 1.0)
    assert _layer_contradiction(thin, same, m, sel, area) != ""
    assert _layer_contradiction(thin, 0.023 / thin, m, sel, area) == ""


@pytest.mark.parametrize("moduli, model", [((2.5, 1.0), "plane-strain"), ((1.0, 2.5), "plane-strain"),
                                           ((2.5, 1.0), "plane-stress")])
def test_true_layers_inverted_and_not_flagged(moduli, model):
    """The exact field of two layers in series (FE, free sides): the ratio within 10 % (measured 2.71 / 0.37 /
    2.51 for 2.5 / 0.4 / 2.5) and no flag."""
    L = LayeredTissue((10.0,), moduli, model=model, size_mm=(20.0, 20.0))
    inv = femreg.invert(L.displacement, region=((1.0, 19.0), (-8.0, 8.0)), uncertainty=False)
    c = inv.mesh.p[:, inv.mesh.t].mean(axis=1)
    ratio = np.median(inv.mu[c[0] < 9.0]) / np.median(inv.mu[c[0] > 11.0])
    truth = moduli[0] / moduli[1]
    assert inv.success, inv.message
    assert abs(ratio / truth - 1.0) < 0.1, (ratio, truth)


def test_layered_tissue_field():
    L = LayeredTissue((8.0, 14.0), (1.0, 3.0, 1.0), level=0.02, size_mm=(20.0, 16.0))
    assert L.modulus(np.array([[4.0, 0.0], [11.0, 0.0], [18.0, 3.0]])) == pytest.approx([1.0, 3.0, 1.0])
    e = L.strain(np.array([[4.0, 0.0], [11.0, 0.0]]))[:, 0]
    assert e[0] < 0 and e[1] < 0 and 2.0 < e[0] / e[1] < 3.5     # the stiff layer strains about 3x less
    assert np.mean(L.strain(np.array([[x, 0.0] for x in np.linspace(0.5, 19.5, 39)]))[:, 0]) == pytest.approx(
        -0.02, rel=0.1)
    with pytest.raises(ValueError):
        LayeredTissue((8.0,), (1.0,))
