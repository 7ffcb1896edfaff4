"""The shear-band forward field (exact strain against finite differences of its own displacement) and the
shear-band / edge metrics of femreg.metrics on profiles with known answers."""
import numpy as np
import pytest

from femreg.metrics import depth_profile, edge_width, shear_band_metrics
from forward.fields import ShearBand


def _fd_strain(field, p, h=1e-4):
    gx = (field.displacement(p + [h, 0]) - field.displacement(p - [h, 0])) / (2 * h)
    gy = (field.displacement(p + [0, h]) - field.displacement(p - [0, h])) / (2 * h)
    return np.column_stack([gx[:, 0], gy[:, 1], 0.5 * (gy[:, 0] + gx[:, 1])])


def test_shear_band_strain_is_the_gradient_of_its_displacement():
    band = ShearBand(depth_mm=12.0, thickness_mm=1.5, slide_mm=0.2, level=0.01)
    rng = np.random.default_rng(3)
    p = np.column_stack([rng.uniform(2, 30, 400), rng.uniform(-15, 15, 400)])
    # keep away from the two faces, where the gradient steps (finite differences straddle them)
    faces = np.array([12.0 - 0.75, 12.0 + 0.75])
    p = p[np.min(np.abs(p[:, :1] - faces), axis=1) > 1e-3]
    e = band.strain(p)
    assert np.allclose(e, _fd_strain(band, p), atol=1e-8)
    assert np.any(band.inside(p)) and np.any(~band.inside(p))
    assert np.allclose(e[band.inside(p), 2], 0.2 / (2 * 1.5))
    assert np.allclose(e[~band.inside(p), 2], 0.0)
    assert np.allclose(e[:, 0], -0.01)


def test_shear_band_slide_is_the_lateral_jump_across_the_band():
    band = ShearBand(depth_mm=10.0, thickness_mm=1.0, slide_mm=0.15, level=0.02)
    u = band.displacement(np.array([[5.0, 3.0], [15.0, 3.0]]))
    assert u[1, 1] - u[0, 1] == pytest.approx(0.15, abs=1e-12)
    assert band.at(0.01).slide_mm == pytest.approx(0.075)
    with pytest.raises(ValueError, match="thickness"):
        ShearBand(thickness_mm=0.0)


def test_shear_band_metrics_on_the_true_profile():
    band = ShearBand(depth_mm=14.0, thickness_mm=1.0, slide_mm=0.15)
    x = np.arange(2.0, 30.0, 0.02)
    img = np.repeat(band.strain(np.column_stack([x, np.zeros_like(x)]))[:, 2:], 5, axis=1)
    m = shear_band_metrics(x, depth_profile(img), (11.0, 17.0))
    assert m["slide"] == pytest.approx(0.15, rel=0.03)          # sampling of the two faces: 0.02 / 1 mm each
    assert m["peak"] == pytest.approx(0.075)
    assert m["depth"] == pytest.approx(14.0, abs=0.02)
    assert m["fwhm"] == pytest.approx(1.0, abs=0.04)


def test_shear_band_metrics_of_a_smeared_band():
    # a Gaussian band: the slide is its area, the depth its centre, the FWHM 2.355 sigma
    x = np.linspace(0.0, 30.0, 1501)
    sigma, area = 1.2, 0.1
    exy = 0.5 * area / (sigma * np.sqrt(2 * np.pi)) * np.exp(-0.5 * ((x - 16.3) / sigma) ** 2) + 0.001
    m = shear_band_metrics(x, exy, (8.0, 24.0))             # the background 0.001 is removed from outside
    assert m["slide"] == pytest.approx(area, rel=1e-3)
    assert m["depth"] == pytest.approx(16.3, abs=0.01)
    assert m["fwhm"] == pytest.approx(2.3548 * sigma, rel=0.01)
    assert m["peak"] == pytest.approx(0.5 * area / (sigma * np.sqrt(2 * np.pi)), rel=1e-3)
    with pytest.raises(ValueError, match="window"):
        shear_band_metrics(x, exy, (10.0, 5.0))


def test_edge_width_of_a_linear_ramp_and_an_erf_step():
    x = np.linspace(0.0, 10.0, 1001)
    ramp = np.clip((x - 4.0) / 2.0, 0.0, 1.0) * 0.02 + 0.01       # 2 mm ramp: 10-90 % is 1.6 mm
    assert edge_width(x, ramp) == pytest.approx(1.6, abs=0.01)
    assert edge_width(x, ramp[::-1] * -1.0) == pytest.approx(1.6, abs=0.01)   # falling, negative
    from scipy.special import erf

    s = 0.3
    step = 0.5 * (1 + erf((x - 5.0) / (np.sqrt(2) * s)))          # 10-90 % of a Gaussian edge: 2.563 sigma
    assert edge_width(x, step, levels=(0.0, 1.0)) == pytest.approx(2.5631 * s, rel=0.01)
    assert np.isnan(edge_width(x, 0.5 + 0 * x + 1e-3 * (x > 5), levels=(0.0, 1.0)))
    with pytest.raises(ValueError, match="equal"):
        edge_width(x, step, levels=(1.0, 1.0))


def test_inclusion_radius_is_checked_before_any_solve():
    from forward.fields import Inclusion

    with pytest.raises(ValueError, match="radius_mm"):
        Inclusion("stiff", radius_mm=20.0)
    with pytest.raises(ValueError, match="radius_mm"):
        Inclusion("stiff", radius_mm=-1.0)


def test_shear_strain_map_ranks_low_correlation_and_small_elements_lower():
    from types import SimpleNamespace

    from femreg.errors import InputError
    from femreg.mesh import roi_mesh
    from femreg.shear import shear_strain_map

    mesh = roi_mesh((200, 60), (0.05, 0.2), (2.0, -6.0), element_size=(1.0, 1.0))
    band = ShearBand(depth_mm=6.0, thickness_mm=2.0, slide_mm=0.2)
    u = band.displacement(mesh.p.T).ravel()                 # interleaved [ux0, uy0, ...]
    n_el = mesh.t.shape[1]
    q = np.full(n_el, 0.99)
    q[: n_el // 2] = 0.9
    res = SimpleNamespace(mesh=mesh, u=u, quality=q, spacing=(0.05, 0.2))
    m = shear_strain_map(res, cell=(0.3, 1.2))
    cen = mesh.p[:, mesh.t].mean(axis=1).T
    ins, far = band.inside(cen), np.abs(cen[:, 0] - 6.0) > 2.0       # elements cut by a face see part of it
    assert np.all((m["exy"][ins] > 0.9 * band.peak_exy) & (m["exy"][ins] <= band.peak_exy + 1e-12))
    assert np.allclose(m["exy"][far], 0.0, atol=1e-12)
    assert np.all(m["sigma"][: n_el // 2] > m["sigma"][n_el // 2:])  # lower NCC, less precise
    coarse = shear_strain_map(res, cell=(0.6, 2.4))                  # larger speckle: fewer cells per element
    assert np.all(coarse["sigma"] > m["sigma"])
    assert np.allclose(m["lateral_cells"], 1.0 / 1.2)
    with pytest.raises(InputError, match="cell"):
        shear_strain_map(res)
    with pytest.raises(InputError, match="cell"):
        shear_strain_map(res, cell=(0.3, -1.0))


def _tensor(lx=4.0, ly=3.0, nx=8, ny=6):
    from skfem import MeshQuad1

    return MeshQuad1.init_tensor(np.linspace(0, lx, nx + 1), np.linspace(0, ly, ny + 1))


def _nodal(mesh, ux, uy):
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2], u[1::2] = ux, uy
    return u


@pytest.mark.parametrize("dilatation", ["edge", "centre"])
def test_shear_traction_weight_scales_the_sliding_jump_only(dilatation):
    import femreg.regularizers as R

    mesh = _tensor()
    x = mesh.p[0]
    slide = _nodal(mesh, 0 * x, 0.01 * np.maximum(x - 2.0, 0.0))            # e_xy kink at x = 2: tangential jump
    squeeze = _nodal(mesh, -0.01 * np.maximum(x - 2.0, 0.0), 0 * x)          # e_xx kink at x = 2: normal jump

    def energy(w, u):
        reg = R.make_regularizer("momentum-stress", alpha=1.0, dilatation=dilatation, delta=1e-16,
                                 shear_traction=w)
        reg.setup(mesh)
        return reg.energy(u) - reg.energy(0 * u)                      # minus the sqrt(delta) floor

    e1, e03 = energy(1.0, slide), energy(0.3, slide)
    # up to the sqrt(delta) floor on the interface (length 3 mm x 1e-8): 3e-8 against 9e-3
    assert e1 > 0.02 and e03 == pytest.approx(0.3 * e1, abs=1e-7)
    n1, n03 = energy(1.0, squeeze), energy(0.3, squeeze)
    assert n1 > 0.02
    assert n03 == pytest.approx(n1, abs=1e-7)
    with pytest.raises(ValueError, match="shear_traction"):
        R.make_regularizer("momentum-stress", shear_traction=0.0)


def test_slip_settings_keep_the_weight_per_area():
    from types import SimpleNamespace

    from femreg.errors import InputError
    from femreg.mesh import roi_mesh
    from femreg.scaling import alpha_scale
    from femreg.shear import slip_settings

    mesh = roi_mesh((400, 100), (0.05, 0.2), (2.0, -10.0), element_size=(1.4, 1.4))
    kw = slip_settings(SimpleNamespace(mesh=mesh, alpha=0.13), axial_mm=0.35, shear_traction=0.05)
    fine = roi_mesh((400, 100), (0.05, 0.2), (2.0, -10.0), element_size=kw["element_size"])
    assert kw["element_size"][0] == 0.35
    # alpha_eff = alpha * 4 / area: the same on both meshes up to the pixel rounding of the element sizes
    assert kw["alpha"] * alpha_scale(fine) == pytest.approx(0.13 * alpha_scale(mesh), rel=0.05)  # 0.98 measured
    assert kw["regularizer_options"] == {"shear_traction": 0.05}
    with pytest.raises(InputError, match="axial_mm"):
        slip_settings(SimpleNamespace(mesh=mesh, alpha=0.13), axial_mm=0.0)
