"""Robust default registration (strategy="auto"): large strain, shear, bending, large motion, peak-hopping repair,
failure reporting, and the paper's procedure kept as strategy="paper".

Small synthetic speckle pairs (femreg.synthetic); each bound is the measured value with a stated margin."""
import numpy as np
import pytest

import femreg
from femreg.cli import main
from femreg.errors import InputError
from femreg.metrics import field_errors
from femreg.synthetic import speckle_image, speckle_pair

SP = (0.025, 0.2)
SHAPE = (600, 80)                      # 15 x 16 mm
YC = 0.5 * (SHAPE[1] - 1) * SP[1]


def compression(e):
    return lambda p: np.column_stack([-e * p[:, 0], 0.5 * e * (p[:, 1] - YC)])


def shear(p):
    th = np.deg2rad(0.1)
    return np.column_stack([-0.01 * p[:, 0] + (0.006 - th) * (p[:, 1] - YC), 0.005 * (p[:, 1] - YC) + th * p[:, 0]])


def bending(p):
    e = 0.002 + 0.016 * p[:, 1] / (SHAPE[1] * SP[1])
    return np.column_stack([-e * p[:, 0], 0.5 * e * (p[:, 1] - YC)])


#: 3 % compression on the small image: registered by three tests below, once per strategy (:func:`pair3`)
THREE = compression(0.03)


@pytest.fixture(scope="module")
def pair3():
    """The 3 % pair (seed 5, 20 dB) and its registration by strategy ("auto": the default call), each computed
    once for this module."""
    ref, mov = speckle_pair(THREE, SHAPE, SP, seed=5, snr_db=20)
    done = {}

    def register(strategy="auto"):
        if strategy not in done:
            kw = {} if strategy == "auto" else {"strategy": strategy}
            done[strategy] = femreg.register(ref, mov, spacing=SP, **kw)
        return done[strategy]
    return register


@pytest.mark.parametrize("field, bound", [
    (THREE, 0.015),    # measured total strain error 0.44 % (axial 0.1 %); paper procedure 372 %
    (shear, 0.05),                 # measured 2.8 %; paper procedure 4.6 %
    (bending, 0.40),               # measured 29 % (paper 247 %): the lateral part (e_yy) of a field that is not
                                   # in equilibrium, which R_P_sigma resists
])
def test_default_registration_large_strain_shear_bending(field, bound, pair3):
    if field is THREE:
        res = pair3()
    else:
        ref, mov = speckle_pair(field, SHAPE, SP, seed=5, snr_db=20)
        res = femreg.register(ref, mov, spacing=SP)
    err = field_errors(res, field)
    assert res.success, res.message
    assert err["exx"] < 0.02, f"axial strain error {100 * err['exx']:.1f} %"     # measured 0.1-0.5 %
    assert err["e"] < bound, f"total strain error {100 * err['e']:.1f} %"
    assert res.quality is not None and res.quality.shape == (res.mesh.t.shape[1],)
    assert np.nanmin(res.quality) > 0.8, np.nanmin(res.quality)                    # measured 0.96


def test_paper_procedure_fails_where_the_default_does_not(pair3):
    # 3 % compression on a small image: the paper's 5 x 9 mm windows decorrelate
    auto = field_errors(pair3(), THREE)["e"]
    paper = field_errors(pair3("paper"), THREE)["e"]
    assert auto < 0.05 and paper > 3 * auto, (auto, paper)


def test_rigid_shift_of_1_9_mm_is_found():
    def f(p):
        return np.column_stack([1.9 - 0.005 * p[:, 0], 0.0025 * (p[:, 1] - YC)])
    ref, mov = speckle_pair(f, (1200, 80), SP, seed=6, snr_db=20)      # 30 mm deep
    res = femreg.register(ref, mov, spacing=SP)
    err = field_errors(res, f)
    assert res.success, res.message
    assert err["ux"] < 0.001, f"axial displacement error {100 * err['ux']:.3f} %"   # measured 0.003 %


def test_injected_one_period_jump_is_repaired():
    ref, mov = speckle_pair(compression(0.01), SHAPE, SP, seed=7, snr_db=20)
    good = femreg.register(ref, mov, spacing=SP)
    stats = femreg.pyramid.speckle_statistics(ref, SP)
    start = good.u.copy()
    p = good.mesh.p
    patch = (np.abs(p[0] - 7.5) < 1.5) & (np.abs(p[1] - 8.0) < 2.0)     # a few interior nodes
    assert 2 <= patch.sum() <= 12, patch.sum()
    start[0::2][patch] += stats.period                                     # one RF period off
    plain = femreg.register(ref, mov, spacing=SP, initial=start, repair=False)
    fixed = femreg.register(ref, mov, spacing=SP, initial=start)
    P = p.T
    e_plain = np.abs(plain.displacement(P)[:, 0] - compression(0.01)(P)[:, 0]).max()
    e_fixed = np.abs(fixed.displacement(P)[:, 0] - compression(0.01)(P)[:, 0]).max()
    assert e_plain > 0.5 * stats.period, e_plain          # without repair Gauss-Newton keeps the hop
    assert e_fixed < 0.1 * stats.period, e_fixed          # repaired: measured 0.01 periods
    assert "reseeded" in fixed.message


def test_unrelated_images_fail_and_cli_exits_1(tmp_path, capsys):
    rng = np.random.default_rng(8)
    a = speckle_image(SHAPE, SP, rng)
    b = speckle_image(SHAPE, SP, rng)
    res = femreg.register(a, b, spacing=SP)
    assert not res.success and "do not match" in res.message, res.message
    np.save(tmp_path / "a.npy", a.astype(np.float32))
    np.save(tmp_path / "b.npy", b.astype(np.float32))
    code = main(["register", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "--spacing", "0.025", "0.2",
                 "-o", str(tmp_path / "r.npz")])
    assert code == 1
    assert "registration failed" in capsys.readouterr().err


def test_numerical_failure_in_cli_exits_1(tmp_path, monkeypatch, capsys):
    ref, mov = speckle_pair(compression(0.01), SHAPE, SP, seed=9)
    np.save(tmp_path / "a.npy", ref.astype(np.float32))
    np.save(tmp_path / "b.npy", mov.astype(np.float32))

    def boom(*a, **k):
        raise FloatingPointError("singular system")
    monkeypatch.setattr(femreg, "register", boom)
    code = main(["register", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "--spacing", "0.025", "0.2",
                 "-o", str(tmp_path / "r.npz")])
    assert code == 1 and "singular system" in capsys.readouterr().err


def test_complex_input_and_unknown_strategy_are_bad_input():
    a = np.ones(SHAPE) + 1j * np.arange(SHAPE[1])
    with pytest.raises(InputError, match="complex"):
        femreg.register(a, a, spacing=SP)
    ref, mov = speckle_pair(compression(0.01), SHAPE, SP, seed=9)
    with pytest.raises(InputError, match="strategy"):
        femreg.register(ref, mov, spacing=SP, strategy="fast")


def test_paper_strategy_is_the_paper_procedure():
    # paper-like: 0.5 % compression, paper probe; "paper" uses the 2 mm mesh and 5 x 9 mm block matching
    shape = (1300, 100)
    ref, mov = speckle_pair(lambda p: np.column_stack([-0.005 * p[:, 0], 0.0025 * (p[:, 1] - 15.0)]), shape,
                            (0.0192, 0.3), seed=10, snr_db=20)
    res = femreg.register(ref, mov, spacing=(0.0192, 0.3), strategy="paper", regularizer="strain")
    assert res.strategy == "paper" and "coarse_pass" not in res.timings and "pyramid_envelopes" not in res.timings
    h = np.diff(np.unique(res.mesh.p[0]))
    assert abs(np.mean(h) - 2.0) < 0.1, np.mean(h)         # 2 mm rounded to the ROI: measured 2.08
    assert res.blockmatch is not None and np.isclose(res.blockmatch.x[1] - res.blockmatch.x[0],
                                                     round(3.75 / 0.0192) * 0.0192, atol=0.02)
    err = field_errors(res, lambda p: np.column_stack([-0.005 * p[:, 0], 0.0025 * (p[:, 1] - 15.0)]))
    assert res.success and err["exx"] < 0.04, err        # measured 2.7 %


def test_regularizer_instance_is_not_changed():
    from femreg.regularizers import make_regularizer

    mine = make_regularizer("momentum-stress", alpha=0.2)
    ref, mov = speckle_pair(compression(0.01), SHAPE, SP, seed=11)
    res = femreg.register(ref, mov, spacing=SP, regularizer=mine, alpha=0.5, element_size=1.0)
    assert mine.alpha == 0.2 and mine.mesh is None
    assert res.alpha == 0.5 and res.alpha_effective == pytest.approx(0.5 * 4.0 / 1.0, rel=0.05)


def test_quality_map_saved_and_loaded(tmp_path):
    ref, mov = speckle_pair(compression(0.01), SHAPE, SP, seed=12)
    res = femreg.register(ref, mov, spacing=SP)
    res.save(tmp_path / "r.npz")
    back = femreg.load_result(tmp_path / "r.npz")
    assert np.allclose(back.quality, res.quality, equal_nan=True) and back.strategy == "auto"


# -- the fast paths of the pyramid and check stages against their plain forms ---------------------------------

def test_global_search_finds_shift_and_strain():
    from femreg import pyramid

    sp, shape = (0.025, 0.2), (1200, 125)

    def f(p):                                      # 2 mm axial, 1.2 mm lateral shift, 5 % compression
        return np.column_stack([2.0 - 0.05 * (p[:, 0] - 15.0), 1.2 + 0.0 * p[:, 1]])
    ref, mov = speckle_pair(f, shape, sp, seed=1, snr_db=20)
    stats = pyramid.speckle_statistics(ref, sp)
    q = pyramid.default_settings(shape, sp, stats).decimation
    er, em = pyramid._decimated_envelopes(ref, mov, q, stats.envelope)
    coef, c = pyramid.global_search(er, em, (q * sp[0], sp[1]), (0.0, 0.0))
    x = np.array([[5.0, 12.0], [25.0, 3.0]])
    err = np.abs(pyramid._affine(coef, x) - f(x)).max()
    assert err < 0.02 and c > 0.9, (err, c)        # measured 0.0015 mm, NCC 0.99


def test_separable_pixel_values_and_elements_match_the_sparse_operator():
    from femreg.mesh import roi_mesh
    from femreg.pixels import PixelQuadrature
    from femreg.repair import _pixel_elements, pixel_values

    mesh = roi_mesh(SHAPE, SP, element_size=(1.3, 1.7))
    quad = PixelQuadrature(mesh, SHAPE, SP, (0.0, 0.0))
    v = np.random.default_rng(0).standard_normal(mesh.p.shape[1])
    assert quad.location.grid is not None
    fast, elem = pixel_values(quad, v), _pixel_elements(quad)
    assert np.abs(fast - quad.P @ v).max() < 1e-12
    assert np.array_equal(elem, quad.location.element)


def test_rf_period_and_moved_mesh_median_match_their_full_forms():
    from skfem import MeshQuad1

    from femreg import pyramid
    from femreg.mesh import roi_mesh
    from femreg.repair import _node_median

    ref, _ = speckle_pair(compression(0.01), SHAPE, SP, seed=13)
    assert pyramid.rf_period(ref, SP) == pytest.approx(pyramid.speckle_statistics(ref, SP).period, rel=1e-12)
    mesh = roi_mesh(SHAPE, SP, element_size=1.0)
    moved = MeshQuad1(mesh.p + 0.05 * np.sin(mesh.p[::-1]), mesh.t)    # same connectivity, nodes moved
    v = np.random.default_rng(1).standard_normal(mesh.p.shape[1])
    assert np.array_equal(_node_median(moved, v), _node_median(mesh, v))


def test_results_with_many_unmatched_elements_are_flagged(pair3):
    # 8 % compression, 3 MHz probe: the paper's procedure locks onto wrong peaks over whole regions (872 % total
    # strain error); measured 37 % of its elements below element NCC 0.3, 0 % for the default
    from forward.fields import compression as uniform
    from forward.pairs import make_pair

    from femreg.repair import MAX_POOR_FRACTION, poor_fraction

    p = make_pair(uniform(0.08), "L3", (50, 40), 30, 0, top_mm=2.0)
    bad = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin, strategy="paper")
    assert poor_fraction(bad.quality) > MAX_POOR_FRACTION
    assert not bad.success and "elements do not match" in bad.message, bad.message
    good = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
    assert good.success and poor_fraction(good.quality) < 0.05, (good.message, poor_fraction(good.quality))
    # 3 % on the small image: 19 % of the paper result's elements are poor -> said (it fails on the peak-hopping
    # check instead: 60 % of its elements one RF period off, tests/test_check.py)
    noted = pair3("paper")
    assert "match poorly" in noted.message, noted.message


def test_default_element_size_is_capped_for_the_momentum_regularisers():
    """Speckle rule max(6 axial cells, 1.1 lateral cells): 3.3 mm for a 3 MHz probe's cell (0.5 x 3.0 mm); the
    momentum regularisers cap it at 1.5 mm (femreg.pyramid.MAX_ELEMENT_SIZE), the strain ones keep it."""
    from femreg import pyramid

    stats = pyramid.SpeckleStats(period=0.5, cell=np.array([0.5, 3.0]), pulse_cell=np.array([0.5, 3.0]))
    shape, sp = (2600, 80), (0.0385, 0.5)                    # 100 x 40 mm
    rule = {r: pyramid.element_rule(r) for r in ("strain", "momentum-stress")}
    assert rule == {"strain": {"axial_cells": 6.0, "max_size": None},
                    "momentum-stress": {"axial_cells": 4.0, "max_size": 1.5}}, rule
    free = pyramid.default_settings(shape, sp, stats, **rule["strain"]).element_size
    capped = pyramid.default_settings(shape, sp, stats, **rule["momentum-stress"]).element_size
    np.testing.assert_allclose(free, 3.3, atol=1e-9)
    np.testing.assert_allclose(capped, 1.5, atol=1e-9)
    ref, mov = speckle_pair(lambda p: np.c_[-0.01 * p[:, 0], 0.005 * p[:, 1]], (1200, 60), (0.0385, 0.5), seed=4)
    h = lambda r: np.ptp(r.mesh.p[0, r.mesh.t[:, 0]])           # noqa: E731  first element's axial size
    assert h(femreg.register(ref, mov, spacing=(0.0385, 0.5), maxiter=2)) <= 1.5 + 0.04
    assert h(femreg.register(ref, mov, spacing=(0.0385, 0.5), regularizer="strain", maxiter=2)) > 1.5 + 0.04


def _rotation(deg, e=0.01):
    """1 % compression and an in-plane rotation by ``deg`` about the probe-face centre (forward's convention)."""
    import forward.fields as F

    return F.compression_rotation(e, deg)


def test_global_search_finds_a_rotation():
    # simulated RF (scatterers moved, PSF fixed), so the speckle decorrelates with the rotation as on a scanner
    from femreg import pyramid
    from forward.pairs import make_pair

    f = _rotation(3.0)
    p = make_pair(f, "L7", (25, 25), 25, seed=3)
    stats = pyramid.speckle_statistics(p.ref, p.spacing)
    st = pyramid.default_settings(p.ref.shape, p.spacing, stats)
    q, ql = st.decimation, st.lateral_decimation
    er, em = pyramid._decimated_envelopes(p.ref, p.mov, q, stats.envelope, ql)
    sp = (q * p.spacing[0], ql * p.spacing[1])
    coef, c = pyramid.global_search(er, em, sp, p.origin)
    flat, c0 = pyramid.global_search(er, em, sp, p.origin, rotations=())
    pts = np.array([[5.0, -10.0], [20.0, 10.0], [12.0, 0.0]])
    err = np.abs(pyramid._affine(coef, pts) - f.displacement(pts)).max()
    err0 = np.abs(pyramid._affine(flat, pts) - f.displacement(pts)).max()
    assert c0 < pyramid.ROTATION_SCAN_NCC                # measured 0.15: the rotation scan runs
    # measured 0.085 mm, NCC 0.48; the angles are 1 degree apart: up to 0.5 degree x 12 mm = 0.1 mm
    assert err < 0.15 and c > 0.3, (err, c)
    assert err0 > 3 * err, (err0, err)                    # shift + strain only: measured 0.92 mm


@pytest.mark.parametrize("deg, probe, size, bound", [
    (2.0, "L12", (30, 30), 0.03),      # measured 0.8 % (586 % with success=True before the rotation scan)
    (3.0, "L7", (20, 20), 0.16),       # measured 10.6 %: the rotation decorrelates the 1.2 mm wide beam's speckle
])
def test_rotated_pairs_register(deg, probe, size, bound):
    from forward.pairs import make_pair

    f = _rotation(deg)
    p = make_pair(f, probe, size, 25, seed=3)
    res = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
    err = field_errors(res, f.displacement, f.strain)
    assert res.success, res.message
    assert err["exx"] < 0.5 * bound and err["e"] < bound, err


def test_rotation_beyond_the_speckle_correlation_is_reported():
    # 4 degrees under a 1.2 mm wide beam: measured 185 % total strain error; the RF solution still differs
    # from the envelope level by whole periods after the repair, which fails the result
    from forward.pairs import make_pair

    f = _rotation(4.0)
    p = make_pair(f, "L7", (20, 20), 25, seed=3)
    res = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
    assert not res.success and "peak hopping remains" in res.message, res.message


def test_strain_stopping_rule_stops_early_with_the_same_strain():
    # 1 % compression + 3 deg under the 15 MHz probe (on the shear pair of this module the energy condition keeps
    # the solve going until the ||du|| / ||u|| rule, 4 iterations either way)
    from forward.pairs import make_pair

    f = _rotation(3.0)
    p = make_pair(f, "L15", (15, 15), 25, seed=3)
    fast = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
    full = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin, strain_tol=0)   # ||du|| / ||u|| alone
    for bad in (-0.1, float("nan"), "1%"):
        with pytest.raises(InputError, match="strain_tol"):
            femreg.register(p.ref, p.mov, spacing=p.spacing, strain_tol=bad)
    assert fast.status == 4 and full.status == 0 and fast.nit < full.nit, (fast.nit, full.nit)   # measured 7, 8
    e_fast, e_full = fast.nodal_strain, full.nodal_strain
    rel = np.sqrt(np.mean((e_fast - e_full) ** 2) / np.mean(e_full ** 2))
    # measured 0.2 %; bound 0.5 % (the rule itself allows more: two steps below 1.5 % shrinking by ~0.7 could
    # leave 1.5 x 0.7 / 0.3 = 3.5 %)
    assert rel < 0.005, rel
    d = field_errors(fast, f.displacement, f.strain)["e"] - field_errors(full, f.displacement, f.strain)["e"]
    assert abs(d) < 0.005, d                                                    # measured -0.03 point


def test_strain_stopping_rule_waits_for_two_small_steps():
    # 1 % compression + 3 deg under the 15 MHz probe: the strain changes per step run 16, 11, 5.4, 0.8, 1.2 %;
    # stopping at the first step below the tolerance gave 2.2 % total strain error, two in a row 1.05 %
    from forward.pairs import make_pair

    f = _rotation(3.0)
    p = make_pair(f, "L15", (15, 15), 25, seed=3)
    res = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
    err = field_errors(res, f.displacement, f.strain)
    assert res.success and res.status == 4, res.message
    assert err["e"] < 0.015, err                    # measured 0.39 % (1.05 % before the energy condition)


def test_strain_stopping_rule_waits_for_the_energy_to_settle():
    # 3 % compression + 3 deg under the 12 MHz probe: steps 5-6 change the strains by 1.3 and 0.25 % while the
    # energy still falls by 6.8e-4 and 6.4e-4 of itself; stopping there gave 0.80 % total strain error (after the
    # refinement pass's extra step), waiting for the energy (steps 8-9: 4.9e-5, 1.7e-5) 0.46 %
    from femreg.solver import GN_ENERGY_TOL
    from forward.pairs import make_pair

    f = _rotation(3.0, e=0.03)
    p = make_pair(f, "L12", (30, 30), 25, seed=3)
    res = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
    err = field_errors(res, f.displacement, f.strain)
    assert res.success and res.status == 4, res.message
    assert err["e"] < 0.006, err                    # measured 0.46 %
    assert 0 < GN_ENERGY_TOL < 6e-4


def test_peak_hopping_island_shared_by_the_coarse_level_is_repaired():
    # 1 % compression + 1 degree under the 3 MHz, 0.5 mm pitch probe: the envelope level and the RF level both
    # held a corner island whole periods off its neighbours (measured 43.6 % total strain error with
    # success=True); the neighbourhood test reseeds it: measured 18.05 % with the default refinement (its
    # marked rows do not stand out: not split, one more step on the unrefined mesh; 14.8 % unrefined)
    from forward.pairs import make_pair

    f = _rotation(1.0)
    p = make_pair(f, "L3", (40, 40), 25, seed=3)
    res = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
    err = field_errors(res, f.displacement, f.strain)
    assert res.success and "peak hopping at" in res.message, res.message
    assert err["e"] < 0.2, err


def test_islands_left_after_the_repair_fail_the_result():
    # 3 degrees under the paper probe's 1.8 mm wide beam, 40 x 30 mm: islands 1-2 periods off (139 % total
    # strain error, returned with success=True before); after the repair 86 %, and nodes still a whole period
    # off their neighbours fail the result
    from forward.pairs import make_pair

    f = _rotation(3.0)
    p = make_pair(f, "paper", (40, 30), 25, seed=3)
    res = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
    assert not res.success and "peak hopping remains" in res.message, res.message
    # and says what to do instead (global envelope NCC measured 0.37; 0.73-0.99 on the benchmark's other pairs
    # and the in vivo pairs, which never get this note)
    assert "strongly decorrelated" in res.message and "track" in res.message, res.message


def test_decorrelated_pair_with_a_tenth_of_its_elements_unmatched_fails():
    # 5 % compression + 5 degrees under the 12 MHz probe: global envelope NCC 0.17, 20 % of the elements below
    # NCC 0.3, 47.7 % total strain error -- returned with success=True before this rule
    from forward.pairs import make_pair

    f = _rotation(5.0, e=0.05)
    p = make_pair(f, "L12", (25, 25), 25, seed=2)
    res = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
    assert not res.success and "on a decorrelated pair" in res.message, res.message
    assert field_errors(res, f.displacement, f.strain)["e"] > 0.15      # it is wrong (measured 47.7 %)


@pytest.mark.slow
def test_neighbourhood_offsets_near_an_inclusion_are_not_forced():
    # 8 % compression of a stiff plane-strain inclusion under L7: about 20 nodes near the inclusion sit a
    # period-sized step off their detrended neighbourhood although they are right; the reseeded solve explains
    # the pair worse (energy 127 -> 204) and is dropped.  Measured 11.1 %, success=True; forcing the reseed gave
    # 13.6 % and a failed result
    import forward.fields as F
    from forward.pairs import make_pair

    f = F.Inclusion("stiff", "plane-strain", 0.08)
    p = make_pair(f, "L7", (30, 30), 25, seed=4)
    res = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin)
    err = field_errors(res, f.displacement, f.strain)
    assert res.success, res.message
    assert err["e"] < 0.125, err
