"""The intrinsic peak-hopping check of ``femreg.register`` (femreg.repair.hop_gain): no ground truth, every
strategy.  A result whose elements sit one RF period off is reported as failed (success=False, "FAILED: ...
peak hopping", CLI exit 1, femreg.track flags the frame); a correct one passes.

Small synthetic speckle pairs (femreg.synthetic, 15 x 16 mm); each bound is the measured value with a stated
margin."""
import numpy as np
import pytest

import femreg
from femreg.cli import main
from femreg.metrics import field_errors
from femreg.pyramid import rf_period
from femreg.repair import HOP_GAIN, MAX_HOPPED_FRACTION, hopped_fraction
from femreg.synthetic import speckle_pair

SP = (0.025, 0.2)
SHAPE = (600, 80)
YC = 0.5 * (SHAPE[1] - 1) * SP[1]


def compression(e):
    return lambda p: np.column_stack([-e * p[:, 0], 0.5 * e * (p[:, 1] - YC)])


def bending(p):
    """Axial strain 0.2 -> 1.8 % across the width: the paper's fixed 5 x 9 mm block matching starts parts of the
    image more than a quarter period off, and Gauss-Newton on RF settles on the neighbouring peak there."""
    e = 0.002 + 0.016 * p[:, 1] / (SHAPE[1] * SP[1])
    return np.column_stack([-e * p[:, 0], 0.5 * e * (p[:, 1] - YC)])


@pytest.fixture(scope="module")
def bend_pair():
    return speckle_pair(bending, SHAPE, SP, seed=5, snr_db=20)


def test_paper_strategy_bending_result_fails_on_peak_hopping(bend_pair):
    ref, mov = bend_pair
    paper = femreg.register(ref, mov, spacing=SP, strategy="paper")
    assert field_errors(paper, bending)["e"] > 1.0          # the result is wrong: measured 247 % total strain error
    assert not paper.success and paper.message.startswith("FAILED") and "peak hopping" in paper.message, \
        paper.message
    assert paper.hop_gain.shape == (paper.mesh.t.shape[1],)
    assert hopped_fraction(paper.hop_gain) > 4 * MAX_HOPPED_FRACTION      # measured 21 % of the elements
    auto = femreg.register(ref, mov, spacing=SP)
    assert auto.success, auto.message
    assert hopped_fraction(auto.hop_gain) == 0.0
    # measured -0.36 on the default refined mesh (quarter-size elements; -1.17 unrefined): below 0 everywhere
    assert np.nanmax(auto.hop_gain) < 0.0


def test_injected_one_period_patch_is_flagged_and_the_correct_result_is_not():
    field = compression(0.01)
    ref, mov = speckle_pair(field, SHAPE, SP, seed=7, snr_db=20)
    good = femreg.register(ref, mov, spacing=SP)
    assert good.success, good.message
    assert np.nanmax(good.hop_gain) < HOP_GAIN - 1.0                   # measured -1.36
    T = rf_period(ref, SP)
    p = good.mesh.p
    patch = (np.abs(p[0] - 7.5) < 2.0) & (np.abs(p[1] - 8.0) < 4.0)
    fully = float(np.mean(np.all(patch[good.mesh.t], axis=0)))          # elements with all nodes one period off
    assert 0.05 < fully < 0.15, fully                                   # 10 of 110
    for sign in (1, -1):
        start = good.u.copy()
        start[0::2][patch] += sign * T
        res = femreg.register(ref, mov, spacing=SP, initial=start, maxiter=0, repair=False)
        assert not res.success and "peak hopping" in res.message, res.message
        # measured 9.1 % (+T) and 10.0 % (-T) against 9.1 % of the elements shifted
        assert abs(hopped_fraction(res.hop_gain) - fully) < 0.03, (sign, hopped_fraction(res.hop_gain), fully)


def test_track_flags_the_hopped_frame_and_cli_exits_1(bend_pair, tmp_path, capsys):
    ref, mov = bend_pair
    seq = femreg.track(np.stack([ref, mov]), spacing=SP, strategy="paper")
    assert seq.flags[0] and "peak hopping" in seq.flags[0], seq.flags
    np.save(tmp_path / "a.npy", ref.astype(np.float32))
    np.save(tmp_path / "b.npy", mov.astype(np.float32))
    args = [str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "--spacing", "0.025", "0.2"]
    assert main(["register", *args, "--strategy", "paper", "-o", str(tmp_path / "p.npz")]) == 1
    assert "peak hopping" in capsys.readouterr().err
    assert main(["register", *args, "-o", str(tmp_path / "a.npz")]) == 0


def test_any_mesh_branch_equals_the_tensor_mesh_branch(bend_pair):
    # femreg.track registers on meshes moved with the tissue: hop_gain then scatters onto the image grid instead
    # of using the tensor mesh's pixel block; both must give the same numbers
    from femreg.image import SplineImage
    from femreg.registration import image_term
    from femreg.repair import envelope_lag_ncc

    ref, mov = bend_pair
    res = femreg.register(ref, mov, spacing=SP, strategy="paper")
    data = image_term(SplineImage(ref, SP, (0.0, 0.0)), SplineImage(mov, SP, (0.0, 0.0)), res.mesh, ref.shape, SP,
                      (0.0, 0.0))
    n_el, T = res.mesh.t.shape[1], rf_period(ref, SP)
    tensor = envelope_lag_ncc(data, res.u, n_el, T, ref.shape, SP)
    data.quad.location.element                       # build the per-pixel element index, then drop the grid
    data.quad.location.grid = None
    anymesh = envelope_lag_ncc(data, res.u, n_el, T, ref.shape, SP)
    assert np.mean(np.isfinite(tensor)) > 0.9
    np.testing.assert_allclose(anymesh, tensor, rtol=0, atol=1e-12)


def test_a_refined_result_is_checked_on_its_unrefined_cells(bend_pair):
    # femreg.register counts the check's fractions on a refined mesh's parent cells: each cell's NCC and hop gain
    # over its pixels at the refined u; with u the coarse field itself they equal the unrefined mesh's own numbers
    from femreg.image import SplineImage
    from femreg.refine import parent_cells, refine_tensor_mesh, transfer
    from femreg.registration import image_term
    from femreg.repair import element_ncc, hop_gain

    ref, mov = bend_pair
    res = femreg.register(ref, mov, spacing=SP, refine=None)
    o = (0.0, 0.0)
    I1, I2 = SplineImage(ref, SP, o), SplineImage(mov, SP, o)
    coarse = image_term(I1, I2, res.mesh, ref.shape, SP, o)
    n_el, T = res.mesh.t.shape[1], rf_period(ref, SP)
    rows = np.ones(len(np.unique(res.mesh.p[0])) - 1, bool)
    cols = np.ones(len(np.unique(res.mesh.p[1])) - 1, bool)
    fine_mesh, sx, sy = refine_tensor_mesh(res.mesh, rows, cols, SP, o, min_size=(0.05, 0.4), levels=2)
    assert sx > 0 and sy > 0 and fine_mesh.t.shape[1] > 4 * n_el
    fine = image_term(I1, I2, fine_mesh, ref.shape, SP, o)
    u = transfer(res.u, res.mesh, fine_mesh)
    parents = parent_cells(res.mesh, fine_mesh)
    assert np.array_equal(np.bincount(parents, minlength=n_el) > 0, np.ones(n_el, bool))
    q0, g0 = element_ncc(coarse, res.u, n_el), hop_gain(coarse, res.u, n_el, T, ref.shape, SP)
    qp = element_ncc(fine, u, fine_mesh.t.shape[1], groups=parents)
    gp = hop_gain(fine, u, fine_mesh.t.shape[1], T, ref.shape, SP, groups=parents)
    assert np.mean(np.isfinite(g0)) > 0.9
    np.testing.assert_allclose(qp, q0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(gp, g0, rtol=0, atol=1e-9)
    # the groups of the identity are the elements themselves
    ident = np.arange(n_el)
    np.testing.assert_allclose(element_ncc(coarse, res.u, n_el, groups=ident), q0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(hop_gain(coarse, res.u, n_el, T, ref.shape, SP, groups=ident), g0, rtol=0,
                               atol=1e-12)
