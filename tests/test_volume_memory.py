"""The memory-saving paths of volume registration give the values of the whole-volume computations they replace:
slabs and chunks (warp, reference gradients, envelopes, result sampling) against one pass, the padded
prefilter against ``np.pad(spline_filter)``, and the storage types of the per-voxel arrays."""
import numpy as np
import pytest
from scipy import ndimage

import femreg.volume as V
import femreg.volume_result as VR
import femreg.voxels as VX
from femreg import _kernels
from femreg.speckle import envelope
from femreg.volume_fields import HexLocator
from femreg.volume_result import VolumeResult
from femreg.voxels import SplineVolume, VoxelGrid, VoxelSSDTerm, roi_mesh_3d

SPACING = (0.02, 0.2, 0.25)


@pytest.fixture(scope="module")
def term():
    rng = np.random.default_rng(5)
    shape = (70, 18, 14)
    ref, mov = rng.standard_normal(shape), rng.standard_normal(shape)
    I1, I2 = SplineVolume(ref, SPACING), SplineVolume(mov, SPACING, keep_data=False)
    mesh = roi_mesh_3d(shape, SPACING, element_size=0.8, margin=0.3)
    return VoxelSSDTerm(VoxelGrid(mesh, shape, SPACING, (0, 0, 0)), I1, I2), I1, ref, mesh, rng


def test_padded_prefilter_equals_np_pad_of_spline_filter():
    rng = np.random.default_rng(0)
    for shape in ((5, 5, 5), (23, 9, 7)):
        d = rng.standard_normal(shape)
        want = np.pad(ndimage.spline_filter(d, order=3, mode="mirror"), 2, mode="reflect")
        S = SplineVolume(d, SPACING)
        assert np.array_equal(S._padded, want)
        assert np.shares_memory(S.coeffs, S._padded)          # one array, not a copy beside it


def test_per_voxel_arrays_are_single_precision_and_the_moving_samples_are_not_kept(term):
    t, I1, ref, _, _ = term
    assert t.ref_values.dtype == np.float32 and all(g.dtype == np.float32 for g in t.g)
    assert t.moving.data is None and I1.data is not None
    # single precision rounds, it does not change: the stored values are the double ones to 2^-24 relative
    assert np.allclose(t.ref_values, ref[t.grid.block], rtol=2 ** -23, atol=0)
    g64 = I1.gradient_at_voxels(t.grid.block)
    assert all(np.allclose(a, b, rtol=2 ** -23, atol=0) for a, b in zip(t.g, g64))


def test_reference_gradient_in_slabs_equals_one_pass(term, monkeypatch):
    t, I1, _, _, _ = term
    whole = I1.gradient_at_voxels(t.grid.block)
    monkeypatch.setattr(VX, "GRADIENT_CHUNK", 1)                    # one voxel row per slab
    assert all(np.array_equal(a, b) for a, b in zip(whole, I1.gradient_at_voxels(t.grid.block)))


@pytest.mark.parametrize("compiled", [True, False])
def test_warp_in_slabs_equals_one_slab(term, monkeypatch, compiled):
    if compiled and not _kernels.HAVE_NUMBA:
        pytest.skip("numba not installed")
    t, _, _, mesh, rng = term
    u = 0.05 * rng.standard_normal(3 * mesh.p.shape[1])
    monkeypatch.setattr(_kernels, "use_compiled", lambda: compiled)
    monkeypatch.setattr(VX, "WARP_CHUNK", 1 << 30)
    one, one_r, one_out = t.warped_moving(u), t.warped_moving(u, t.ref_values), t.outside_mask(3 * u)
    monkeypatch.setattr(VX, "WARP_CHUNK", 100)                      # slabs of one voxel row
    assert len(t._slabs()) == t.shape[0]
    assert np.allclose(t.warped_moving(u), one, rtol=0, atol=1e-13)
    assert np.allclose(t.warped_moving(u, t.ref_values), one_r, rtol=0, atol=1e-13)
    assert np.array_equal(t.outside_mask(3 * u), one_out)
    assert one_out.any() and not one_out.all()                      # the mask test sees both kinds of voxel


def test_fresh_term_shares_the_reference_arrays_and_drops_weights_and_hessian(term):
    t, _, _, _, _ = term
    t2 = t.fresh()
    t2.w = np.zeros(t.shape)
    assert t2.g[0] is t.g[0] and t2.ref_values is t.ref_values
    assert t._w is None and t2._H is None


def test_envelope_and_rf_period_by_column_blocks_equal_whole_volume(monkeypatch):
    rng = np.random.default_rng(2)
    vol = rng.standard_normal((64, 7, 5))
    whole = V._decimate(envelope(vol.reshape(64, -1)).reshape(vol.shape), 4)
    monkeypatch.setattr(V, "COLUMN_CHUNK_3D", 64 * 3)               # 3 lines per block, the last one short
    assert np.array_equal(V._envelope_3d(vol, 4), whole)
    from femreg.speckle import rf_period
    assert V._rf_period_3d(vol, SPACING) == pytest.approx(rf_period(vol.reshape(64, -1), SPACING[:2]), rel=1e-12)


def test_result_sampling_in_chunks_and_on_grid_in_slabs_equal_one_pass(term, monkeypatch):
    _, _, _, mesh, rng = term
    u = 0.05 * rng.standard_normal(3 * mesh.p.shape[1])
    shape = (70, 18, 14)
    res = VolumeResult(mesh, u, shape=shape, spacing=SPACING, origin=(0, 0, 0),
                       quality=rng.uniform(size=mesh.t.shape[1]))
    pts = res.voxel_points()
    loc = HexLocator(mesh)
    whole = loc.sample(u, pts, nodal_strain=res.nodal_strain, chunk=len(pts))
    parts = loc.sample(u, pts, nodal_strain=res.nodal_strain, chunk=997)
    assert all(np.array_equal(whole[k], parts[k], equal_nan=True) for k in whole)
    monkeypatch.setattr(VR, "SAMPLE_CHUNK", 3 * 18 * 14)             # slabs of 3 axial rows
    grid = res.on_grid()
    for k, v in whole.items():
        assert np.array_equal(grid[k], v.reshape(shape), equal_nan=True)
    assert np.isnan(grid["ux"]).any() and np.isfinite(grid["quality"]).any()   # both sides of the mesh edge


def test_ncc_by_slabs_equals_the_whole_volume_formula(term):
    from femreg.image import ncc

    t, _, _, mesh, rng = term
    u = 0.05 * rng.standard_normal(3 * mesh.p.shape[1])
    want = ncc(np.asarray(t.ref_values, float), t.warped_moving(u))
    assert t.ncc(u) == pytest.approx(want, rel=1e-12, abs=1e-14)
    assert abs(want) > 1e-3             # not two uncorrelated zeros


def test_mask_weights_are_stored_as_a_mask_and_give_the_values_of_the_float_weights(term):
    """mask_outside's weights (w0 or 0) are kept as one byte per voxel; energy, gradient and Hessian are those of
    the same weights as a float array, exactly."""
    t, _, _, mesh, _ = term
    u = 0.15 * np.random.default_rng(11).standard_normal(3 * mesh.p.shape[1])
    out = t.outside_mask(u)
    a = t.fresh()
    a.w = np.where(out, 0.0, a.w0)
    assert a._w is None and a._keep.dtype == bool and out.any() and not out.all()
    b = t.fresh()
    b._w, b._keep = np.where(out, 0.0, b.w0), None                 # the float representation
    assert np.array_equal(a.w, b.w)
    assert a.energy(u) == b.energy(u)
    assert np.array_equal(a.gradient(u), b.gradient(u))
    assert (a.hessian() != b.hessian()).nnz == 0
    c = t.fresh()
    c.w = np.where(out, 0.5 * c.w0, c.w0)                          # other weights stay floats
    assert c._keep is None and c._w.dtype == float
