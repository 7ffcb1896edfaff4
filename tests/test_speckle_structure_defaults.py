"""femreg.pyramid.image_settings: register's block matching (decimation, windows, search) sized from the speckle's
own cell (femreg.speckle.speckle_cell) where echo structure widens the whole envelope's cell, the element size as
before; uniform speckle keeps its settings; on a layered echogenicity the registration succeeds where the
envelope cell's windows failed it."""
import numpy as np
import pytest

import femreg
import femreg.pyramid as pyr
from femreg.pyramid import default_settings, element_rule, image_settings
from femreg.speckle import speckle_cell, speckle_statistics


def _gain(shape, spacing, seed, db=6.0, patch_mm=(2.0, 10.0)):
    """Smooth random echogenicity, ``db`` dB RMS, Gaussian patches of FWHM ``patch_mm`` (axial, lateral) mm."""
    from scipy.ndimage import gaussian_filter

    g = gaussian_filter(np.random.default_rng(seed).standard_normal(shape),
                        (patch_mm[0] / spacing[0] / 2.355, patch_mm[1] / spacing[1] / 2.355), mode="wrap")
    return 10.0 ** (db * g / g.std() / 20.0)


@pytest.fixture(scope="module")
def layered():
    """Paper probe, 40 x 30 mm, 30 dB, a stiff inclusion under 1 % compression, the same 6 dB RMS echogenicity in
    2 x 10 mm patches multiplying both frames."""
    from forward import fields as F
    from forward.pairs import make_pair

    p = make_pair(F.Inclusion("stiff", "plane-strain", 0.01), "paper", seed=0)
    g = _gain(p.ref.shape, p.spacing, 100)
    return p, np.asarray(p.ref, float) * g, np.asarray(p.mov, float) * g


def _total_error(res, p, n=40):
    """RMS error of (e_xx, e_yy, 2 e_xy) over the middle 80 % of the image, % of the true strain's RMS."""
    sh, sp, o = np.array(p.ref.shape), np.array(p.spacing), np.array(p.origin)
    x, y = np.meshgrid(*(np.linspace(o[k] + 0.1 * sh[k] * sp[k], o[k] + 0.9 * sh[k] * sp[k], n) for k in (0, 1)),
                       indexing="ij")
    pts = np.c_[x.ravel(), y.ravel()]
    e, t = res.strain(pts), p.field.strain(pts)
    ok = np.all(np.isfinite(e), axis=1)
    w = np.array([1.0, 1.0, 2.0])
    return 100.0 * np.sqrt(np.mean(((e[ok] - t[ok]) * w) ** 2) / np.mean((t[ok] * w) ** 2))


def test_windows_from_the_speckle_cell_elements_as_before(layered):
    p, ref, _ = layered
    stats = speckle_statistics(ref, p.spacing)
    own = speckle_cell(ref, p.spacing, stats=stats)
    # measured: envelope 1.23 x 4.2 mm, speckle 0.42 x 1.8 mm
    assert np.all(own < 0.5 * stats.cell), (own, stats.cell)
    _, st = image_settings(ref, p.spacing, regularizer="momentum-stress")
    old = default_settings(ref.shape, p.spacing, stats, **element_rule("momentum-stress"))
    assert np.allclose(st.search, [3.0 * own[0], 2.0 * own[1]])
    assert np.all(st.search < 0.5 * old.search) and st.decimation < old.decimation
    assert np.array_equal(st.element_size, old.element_size)


def test_uniform_speckle_keeps_its_settings():
    from forward import fields as F
    from forward.pairs import make_pair

    for probe in ("paper", "L12"):
        p = make_pair(F.compression(0.01), probe, seed=0)
        stats, st = image_settings(p.ref, p.spacing, regularizer="momentum-stress")
        old = default_settings(p.ref.shape, p.spacing, stats, **element_rule("momentum-stress"))
        for k in ("element_size", "window", "search"):
            assert np.array_equal(getattr(st, k), getattr(old, k)), (probe, k)
        assert (st.decimation, st.lateral_decimation) == (old.decimation, old.lateral_decimation)


def test_layered_pair_registers(layered, monkeypatch):
    p, ref, mov = layered
    new = femreg.register(ref, mov, spacing=p.spacing, origin=p.origin)
    # the envelope cell's windows (a ratio of 0 never takes the speckle cell): measured 110.7 % and failed
    monkeypatch.setattr(pyr, "STRUCTURE_RATIO", 0.0)
    old = femreg.register(ref, mov, spacing=p.spacing, origin=p.origin)
    e_new, e_old = _total_error(new, p), _total_error(old, p)
    # measured 9.5 %; the margin leaves room for round-off in the solve
    assert new.success and e_new < 15.0, e_new
    assert e_old > 50.0 and e_old - e_new > 40.0, (e_old, e_new)
