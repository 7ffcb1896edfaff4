"""femreg.quality: no-ground-truth measures on fields and image pairs whose answers are known."""
import numpy as np
import pytest

from femreg import InputError, RegistrationResult
from femreg.mesh import roi_mesh
from femreg.quality import consistency, hourglass, image_energy, strain_snr, window_mask
from femreg.synthetic import speckle_image, warp_image

SHAPE, SPACING, ORIGIN = (300, 40), (0.05, 0.2), (1.0, -2.0)


def _result(field, mesh=None):
    """RegistrationResult with nodal values of ``field(points) -> (n, 2)`` on the ROI mesh."""
    mesh = mesh if mesh is not None else roi_mesh(SHAPE, SPACING, ORIGIN, element_size=1.0, margin=0.5)
    v = field(mesh.p.T)
    u = np.empty(2 * mesh.p.shape[1])
    u[0::2], u[1::2] = v[:, 0], v[:, 1]
    return RegistrationResult(mesh, u, shape=SHAPE, spacing=SPACING, origin=ORIGIN)


def linear(a=-0.01, b=0.004, c=(0.0, 0.0)):
    return lambda p: np.column_stack([a * p[:, 0] + c[0], b * p[:, 1] + c[1]])


def test_window_mask_counts_pixel_centres():
    m = window_mask(SHAPE, SPACING, ORIGIN, ((2.0, 3.0), (-1.0, 0.0)))
    # axial centres 1 + 0.05 i in [2, 3]: i = 20..40 (21); lateral -2 + 0.2 j in [-1, 0]: j = 5..10 (6)
    assert m.sum() == 21 * 6, m.sum()
    with pytest.raises(InputError, match="window"):
        window_mask(SHAPE, SPACING, ORIGIN, ((3.0, 2.0), (0, 1)))


def test_strain_snr_of_a_linear_field_is_exact():
    s = strain_snr(_result(linear(-0.01)), ((3.0, 10.0), (-1.0, 3.0)))
    assert abs(s["mean"] + 0.01) < 1e-12 and s["std"] < 1e-12, s
    rng = np.random.default_rng(0)
    noisy = _result(lambda p: linear(-0.01)(p) + 1e-3 * rng.standard_normal(p.shape))
    s = strain_snr(noisy, ((3.0, 10.0), (-1.0, 3.0)))
    assert 0 < s["snr"] < np.inf and abs(s["snr"] - abs(s["mean"]) / s["std"]) < 1e-12, s
    with pytest.raises(InputError, match="pixels"):
        strain_snr(noisy, ((100.0, 101.0), (0.0, 1.0)))


def test_consistency_zero_for_equal_and_offset_for_shifted_fields():
    a = _result(linear())
    c = consistency(a, a)
    assert c["rms_du"] == 0 and c["rms_dexx"] == 0 and c["rms_u"] > 0, c
    b = _result(linear(c=(0.003, -0.004)), mesh=a.mesh)   # a rigid shift of 5 um changes no strain
    c = consistency(a, b)
    assert abs(c["rms_du"] - 0.005) < 1e-12 and c["rms_dexx"] < 1e-12, c
    cw = consistency(a, b, window=((3.0, 5.0), (0.0, 2.0)))
    assert cw["n"] < c["n"] and abs(cw["rms_du"] - 0.005) < 1e-12, (cw, c)


def test_image_energy_drops_at_the_true_field_and_is_zero_for_identical_frames():
    rng = np.random.default_rng(3)
    ref = speckle_image(SHAPE, SPACING, rng)
    field = linear(-0.01, 0.004)
    mov = warp_image(ref, SPACING, ORIGIN, field)
    e = image_energy(_result(field), ref, mov)
    half = image_energy(_result(linear(-0.005, 0.002)), ref, mov)
    # the true field explains most of the mismatch (what is left: cubic vs quintic interpolation of ~3 samples
    # per RF period), and more than a field of half the size
    assert e["psi_zero"] > 0 and e["reduction"] > 0.9 and e["reduction"] > half["reduction"] + 0.1, (e, half)
    assert e["psi_zero"] == half["psi_zero"]
    assert np.isnan(e["psi_initial"]) and np.isnan(e["ncc_initial"])  # no block-matching field on this result
    e0 = image_energy(_result(lambda p: np.zeros_like(p)), ref, ref)
    assert e0["psi_zero"] == 0 and e0["psi_final"] == 0 and np.isnan(e0["reduction"]), e0
    with pytest.raises(InputError, match="grid"):
        image_energy(_result(field), ref[:-1], mov[:-1])


def test_hourglass_sees_a_checkerboard_and_not_an_affine_field():
    a = _result(linear(c=(0.01, 0.02)))
    hg = hourglass(a)
    assert hg["ux"] < 1e-15 and hg["uy"] < 1e-15, hg
    # add a node-to-node checkerboard of 2 um to uy on the tensor mesh
    xs, ys = np.unique(a.mesh.p[0]), np.unique(a.mesh.p[1])
    i = np.searchsorted(xs, a.mesh.p[0])
    j = np.searchsorted(ys, a.mesh.p[1])
    u = a.u.copy()
    u[1::2] += 0.002 * (-1.0) ** (i + j)
    b = RegistrationResult(a.mesh, u, shape=SHAPE, spacing=SPACING, origin=ORIGIN)
    hg = hourglass(b)
    assert hg["ux"] < 1e-15 and abs(hg["uy"] - 0.002) < 1e-12, hg


def test_hourglass_of_a_triangle_mesh_is_bad_input():
    from types import SimpleNamespace

    from skfem import MeshTri1

    m = MeshTri1()
    with pytest.raises(InputError, match="quadrilateral"):
        hourglass(SimpleNamespace(mesh=m, u=np.zeros(2 * m.p.shape[1])))
