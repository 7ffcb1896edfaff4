"""R_P_sigma's lambda_bar taken from the data's lateral-to-axial strain ratio (femreg.strategy.data_lambda_bar)."""
import numpy as np
import pytest

from femreg.fields import lateral_ratio
from femreg.material import lambda_bar_from_ratio, model_ratio
from femreg.strategy import LAMBDA_BAR_MODELS, PLANE_STRAIN_RATIO, data_lambda_bar, lambda_bar_follows_data


def _mesh():
    from skfem import MeshQuad1
    return MeshQuad1.init_tensor(np.linspace(0.0, 20.0, 11), np.linspace(-10.0, 10.0, 11))


def _affine(mesh, exx, eyy, exy=0.0):
    x, y = mesh.p
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2] = exx * x + exy * y
    u[1::2] = eyy * y + exy * x
    return u


@pytest.mark.parametrize("lb", [0.0, 2.0, 9.0, 99.0])
def test_lambda_bar_from_ratio_inverts_the_model_ratio(lb):
    assert lambda_bar_from_ratio(model_ratio(lb)) == pytest.approx(lb, rel=1e-9, abs=1e-12)


def test_lambda_bar_from_ratio_edges():
    assert model_ratio(2.0) == 0.5                        # incompressible plane stress
    assert lambda_bar_from_ratio(1.0) == np.inf
    assert np.isnan(lambda_bar_from_ratio(np.nan))


@pytest.mark.parametrize("ratio", [0.3, 0.5, 0.7, 0.98])
def test_lateral_ratio_of_a_uniaxial_field(ratio):
    mesh = _mesh()
    u = _affine(mesh, -0.01, 0.01 * ratio)
    from femreg.fields import element_strains
    assert lateral_ratio(element_strains(mesh.p, mesh.t, u), mesh) == pytest.approx(ratio, rel=1e-9)


def test_data_lambda_bar_reads_plane_strain_or_plane_stress_and_falls_back_without_axial_strain():
    mesh = _mesh()
    stress, strain = LAMBDA_BAR_MODELS
    assert (stress, strain, PLANE_STRAIN_RATIO) == (2.0, 9.0, 0.75)
    assert data_lambda_bar(mesh, _affine(mesh, -0.01, 0.0098))[0] == strain      # plane strain, nu 0.495: 0.98
    assert data_lambda_bar(mesh, _affine(mesh, -0.01, 0.0076))[0] == strain
    lb, r = data_lambda_bar(mesh, _affine(mesh, -0.01, 0.0074))                  # just under the midway ratio
    assert lb == stress and r == pytest.approx(0.74)
    assert data_lambda_bar(mesh, _affine(mesh, -0.01, 0.005))[0] == stress       # incompressible plane stress
    lb, r = data_lambda_bar(mesh, _affine(mesh, 0.0, 0.0, 0.01))                # pure shear: no axial strain
    assert np.isnan(r) and lb == stress
    lb, r = data_lambda_bar(mesh, _affine(mesh, -0.01, 0.013))                  # more than incompressible
    assert r == pytest.approx(1.3) and lb == stress


def test_only_r_p_sigma_by_name_under_auto_follows_the_data():
    assert lambda_bar_follows_data("auto", "momentum-stress", None)
    assert not lambda_bar_follows_data("paper", "momentum-stress", None)
    assert not lambda_bar_follows_data("auto", "momentum-strain", None)
    assert not lambda_bar_follows_data("auto", "momentum-stress", {"lambda_bar": 2.0})
    assert not lambda_bar_follows_data("auto", "momentum-stress", None, maxiter=0)


def _errors(res, data, sl):
    from benchmarks.robustness import errors, truth
    from forward.pairs import PROBES
    return errors(res.on_grid(), truth(data, None, sl), sl, PROBES["L7"].wavelength_mm)


@pytest.fixture(scope="module")
def plane_strain_pair():
    import forward.fields as F
    from forward.pairs import make_pair
    return make_pair(F.Inclusion("stiff", "plane-strain", 0.02, radius_mm=4.0), "L7", (24.0, 20.0), 30.0, 5,
                     top_mm=8.0)


def test_plane_strain_pair_takes_a_plane_strain_lambda_bar(plane_strain_pair):
    import femreg
    from benchmarks.robustness import roi_slices

    d = plane_strain_pair
    res = femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin)
    fixed = femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin,
                            regularizer_options={"lambda_bar": 2.0})
    assert res.success and fixed.success
    assert "plane strain (lambda_bar 9) from the lateral-to-axial strain ratio" in res.message
    assert "lambda_bar" not in fixed.message
    assert res.lambda_bar == 9.0 and fixed.lambda_bar == 2.0


def test_the_lambda_bar_that_solved_is_kept_in_the_result_file(plane_strain_pair, tmp_path):
    import femreg
    from femreg.errors import FileFormatError

    d = plane_strain_pair
    res = femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin, refine=None)
    res.save(tmp_path / "r.npz")
    assert femreg.load_result(tmp_path / "r.npz").lambda_bar == 9.0
    strain = femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin, regularizer="strain", refine=None)
    strain.save(tmp_path / "s.npz")
    assert strain.lambda_bar is None and femreg.load_result(tmp_path / "s.npz").lambda_bar is None
    bad = dict(np.load(tmp_path / "r.npz", allow_pickle=False))
    bad["lambda_bar"] = np.array(-1.0)
    np.savez(tmp_path / "bad.npz", **bad)
    with pytest.raises(FileFormatError, match="lambda_bar"):
        femreg.load_result(tmp_path / "bad.npz")


def test_plane_strain_pair_gains_with_the_plane_strain_lambda_bar(plane_strain_pair):
    import femreg
    from benchmarks.robustness import roi_slices

    d = plane_strain_pair
    res = femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin)
    fixed = femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin,
                            regularizer_options={"lambda_bar": 2.0})
    sl = roi_slices(res.shape, res.spacing)
    e_auto, e_fixed = _errors(res, d, sl)["e"], _errors(fixed, d, sl)["e"]
    # measured 0.0985 against 0.1221 (total strain error): bound at half the gain
    assert e_auto < e_fixed - 0.012, (e_auto, e_fixed)


def test_plane_stress_pair_keeps_r_p_sigma_exactly():
    import femreg
    import forward.fields as F
    from forward.pairs import make_pair

    d = make_pair(F.Inclusion("soft", "plane-stress", 0.01, radius_mm=4.0), "L7", (24.0, 20.0), 30.0, 6, top_mm=8.0)
    res = femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin)
    fixed = femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin,
                            regularizer_options={"lambda_bar": 2.0})
    assert "lambda_bar" not in res.message
    np.testing.assert_array_equal(res.u, fixed.u)


def test_every_quadrant_must_read_plane_strain():
    from femreg.fields import element_strains, quadrant_ratios

    mesh = _mesh()                                  # x 0-20 mm, y -10-10 mm
    u = _affine(mesh, -0.01, 0.0098)
    assert np.allclose(quadrant_ratios(element_strains(mesh.p, mesh.t, u), mesh), 0.98)
    assert data_lambda_bar(mesh, u)[0] == 9.0
    # the deep-right quadrant expands as plane stress: the image's median still reads 0.98, the quadrant 0.5
    x, y = mesh.p
    deep_right = (x >= 10.0) & (y >= 0.0)
    u[1::2] = np.where(deep_right, 0.005 * y, 0.0098 * y)
    q = quadrant_ratios(element_strains(mesh.p, mesh.t, u), mesh)
    assert np.allclose(q[:3], 0.98) and q[3] == pytest.approx(0.5)
    lb, r = data_lambda_bar(mesh, u)
    assert r == pytest.approx(0.98) and lb == 2.0
