"""Large strain: companded block matching and the automatic coarse-to-fine pass of femreg.register (strategy="paper")."""
import numpy as np

import femreg
from femreg.blockmatch import block_match
from femreg.synthetic import speckle_pair

SP = (0.0192, 0.3)
SHAPE = (1300, 100)          # 25 x 30 mm


def _field(strain):
    def u(p):
        return np.column_stack([-strain * p[:, 0], 0.5 * strain * (p[:, 1] - 15.0)])
    return u


def test_companded_block_matching_measures_large_strain():
    # 1.5 % compression: a 5 mm window is squeezed by ~4 samples, the plain NCC peaks drop to ~0.55
    ref, mov = speckle_pair(_field(0.015), SHAPE, SP, seed=3)
    plain = block_match(ref, mov, SP, compand_strain=None)
    bm = block_match(ref, mov, SP)
    assert np.median(bm.ncc) > np.median(plain.ncc) + 0.2, (np.median(plain.ncc), np.median(bm.ncc))
    assert abs(bm.global_strain() - 0.015) < 0.001, f"global strain {bm.global_strain():.4f}, expected 0.015"
    assert abs(bm.affine_fit()[1, 0] + 0.015) < 0.001


def test_coarse_pass_only_at_large_strain():
    for strain, expect_coarse in ((0.004, False), (0.015, True)):
        ref, mov = speckle_pair(_field(strain), SHAPE, SP, seed=4)
        res = femreg.register(ref, mov, spacing=SP, regularizer="strain", strategy="paper")
        assert ("coarse_pass" in res.timings) == expect_coarse, (strain, res.timings.keys())
        pts = res.mesh.p.T
        err = np.abs(res.displacement(pts)[:, 0] - _field(strain)(pts)[:, 0])
        assert np.sqrt(np.mean(err ** 2)) < 0.2 * SP[0], \
            f"strain {strain}: axial RMS error {np.sqrt(np.mean(err ** 2)) / SP[0]:.3f} samples"
