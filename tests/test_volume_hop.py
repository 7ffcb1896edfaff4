"""The envelope-lag peak-hopping check on volumes (femreg.volume.hop_check, femreg.repair.envelope_lag_ncc_3d):
a correct registration is not flagged, a displacement one RF period off over a block of elements is."""
from __future__ import annotations

import numpy as np
import pytest

import femreg
from femreg.repair import HOP_GAIN, MAX_HOPPED_FRACTION, envelope_lag_ncc_3d, hopped_fraction, lag_gain
from femreg.volume import _rf_period_3d, hop_check
from femreg.voxels import SplineVolume, VoxelGrid, VoxelSSDTerm, roi_mesh_3d

from _volumes import affine_field, volume_pair

SPACING = (0.02, 0.2, 0.25)


@pytest.fixture(scope="module")
def pair():
    shape = (300, 30, 24)
    field, _ = affine_field(0.01, 0.005, 0.5, centre=np.array(shape) * SPACING / 2)
    ref, mov, spacing, origin = volume_pair(field, shape=shape, f_mhz=7.0, seed=0)
    return ref, mov, spacing, origin, field


def _doctored(mesh, u, period):
    """``u`` with u_x one RF period larger on the nodes of a block of about 2 x 2.5 x 3 mm."""
    p = mesh.p
    blk = (p[0] > 2.0) & (p[0] < 4.5) & (p[1] > 1.5) & (p[1] < 4.0)
    out = np.array(u, float)
    out[0::3][blk] += period
    return out, blk[mesh.t].all(axis=0)         # and the elements whose 8 nodes are all moved


def test_a_correct_volume_registration_is_not_flagged_as_hopping(pair):
    ref, mov, spacing, _, _ = pair
    res = femreg.register(ref, mov, spacing=spacing, element_size=1.0)
    assert res.success, res.message
    assert res.hop_gain.shape == (res.mesh.t.shape[1],) and np.all(np.isfinite(res.hop_gain))
    # measured: largest gain -2.32 (the envelope correlation peaks at lag 0), 0 % hopped
    assert hopped_fraction(res.hop_gain) == 0.0
    assert np.max(res.hop_gain) < HOP_GAIN - 1.0
    assert "peak hopping" not in res.message


def test_a_volume_displacement_one_period_off_over_a_block_is_flagged_with_its_fraction(pair):
    ref, mov, spacing, origin, field = pair
    r1, m1 = (v / np.sqrt(np.mean(v ** 2)) for v in (ref, mov))
    T = _rf_period_3d(r1, spacing)
    assert 0.1 < T < 0.12                       # 7 MHz: lambda / 2 = 0.11 mm
    mesh = roi_mesh_3d(ref.shape, spacing, element_size=1.0)
    data = VoxelSSDTerm(VoxelGrid(mesh, ref.shape, spacing, origin), SplineVolume(r1, spacing, origin),
                        SplineVolume(m1, spacing, origin))
    truth = field(mesh.p.T).ravel()
    bad, inside = _doctored(mesh, truth, T)
    g0, notes0 = hop_check(data, data.warped_moving(truth), T)
    assert hopped_fraction(g0) == 0.0 and notes0 == []
    g1, notes1 = hop_check(data, data.warped_moving(bad), T)
    frac = hopped_fraction(g1)
    # measured 17 % flagged (12.5 % of the elements lie wholly in the block, the rest straddle its faces)
    assert frac >= inside.mean() > MAX_HOPPED_FRACTION
    assert len(notes1) == 1 and f"{frac:.0%} of the elements" in notes1[0]
    # the same per-element computation as hop_gain, lag 0 is the match at u itself: every element wholly in the
    # block matches better at u_x - T
    c = envelope_lag_ncc_3d(data, data.warped_moving(bad), T)
    assert np.array_equal(lag_gain(c), g1, equal_nan=True)
    assert np.all(c[0, inside] > c[1, inside]) and np.all(g1[inside] > HOP_GAIN)
    # through register: a start one period off over the block, one iteration, no repair -> FAILED naming it
    res = femreg.register(ref, mov, spacing=spacing, mesh=mesh, initial=bad, maxiter=1, repair=False)
    f = hopped_fraction(res.hop_gain)
    assert not res.success and f > MAX_HOPPED_FRACTION, (f, res.message)
    assert f"peak hopping: {f:.0%} of the elements match the envelope better one RF period" in res.message
