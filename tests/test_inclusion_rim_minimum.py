"""benchmarks/inclusion_rim.py --minimum: the solver's own field at the finer pass's own weight."""
import pytest

pytest.importorskip("forward")


def _case():
    from benchmarks.inclusion_sizes import CASES
    from benchmarks.robustness import make_data, roi_slices, truth

    case = next(c for c in CASES if c.name == "held_r4_3pc_L12")
    d = make_data(case)
    sl = roi_slices(d.ref.shape, d.spacing)
    return d, sl, truth(d, case, sl), case


@pytest.mark.slow
def test_the_minimum_is_the_solvers_field_not_the_start_the_check_hands_back():
    # held-out r 4 mm under 12 MHz (finer pass's noise factor 0.25), measured 2026-12-08: default 4.37 %, the
    # minimum at the pass's weight 4.25 % (passes the check), at the unrefined weight 4.96 % (fails it: the
    # image term rose over the exact start's); the former row showed the exact start, 4.05 %
    import warnings

    import femreg
    from benchmarks.inclusion_rim import objective_minimum
    from benchmarks.robustness import errors
    from forward.pairs import PROBES

    d, sl, t, case = _case()
    wl = PROBES[case.probe].wavelength_mm
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        default = 100 * errors(femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin).on_grid(), t, sl,
                               wl)["e"]
    g, passed = objective_minimum(d, "pass")
    e_pass = 100 * errors(g, t, sl, wl)["e"]
    assert passed
    # below the default (0.12 points measured), by less than 0.3
    assert default - 0.3 < e_pass < default - 0.03
    g, passed = objective_minimum(d, "unrefined")
    e_unref = 100 * errors(g, t, sl, wl)["e"]
    assert not passed
    # the solver's field (0.59 points over the default measured), not the exact start (0.32 under)
    assert e_unref > default + 0.3
