"""More Gauss-Newton steps on the finer refinement pass under R_P_sigma's plane-stress model
(femreg.refine.Refinement.fine_maxiter_stress, femreg.refine.plane_stress_model)."""
import dataclasses

import pytest

import femreg
from femreg.refine import DEEP_REFINEMENT, plane_stress_model
from femreg.regularizers import make_regularizer
from _strain_error import total_strain_error

pytest.importorskip("forward")


def _pair(plane):
    from forward import fields as F
    from forward.pairs import make_pair

    return make_pair(F.Inclusion("soft", plane, 0.02, radius_mm=4.0), "L7", (20, 20), 20, 6, top_mm=3.0)


def _both(d):
    out = []
    for opts in ("auto", dataclasses.replace(DEEP_REFINEMENT, fine_maxiter_stress=None)):
        res = femreg.register(d.ref, d.mov, spacing=d.spacing, origin=d.origin, refine=opts)
        (p,) = [q for q in res.refinement.passes if q["fine"]]
        out.append((total_strain_error(res, d), p["nit"], res))
    return out


def test_the_plane_stress_model_takes_more_steps_and_gains():
    # a soft plane-stress disk under 7.5 MHz (none of the benchmarks holds it): 5 steps against 2, measured
    # 7.89 -> 7.28 %, bound 0.4 point
    (e_new, n_new, _), (e_old, n_old, _) = _both(_pair("plane-stress"))
    assert n_old == 2 and n_new > 2, (n_new, n_old)
    assert e_new < e_old - 0.4, (e_new, e_old)


def test_a_plane_strain_solve_keeps_its_steps():
    # the same disk in plane strain: register re-solves it with plane strain's lambda_bar, so nothing changes
    (e_new, n_new, r_new), (e_old, n_old, _) = _both(_pair("plane-strain"))
    assert "plane strain (lambda_bar 9)" in r_new.message
    assert n_new == n_old and e_new == e_old, (n_new, n_old, e_new, e_old)


def test_which_regularisers_are_the_plane_stress_model():
    assert plane_stress_model(make_regularizer("momentum-stress"))
    assert not plane_stress_model(make_regularizer("momentum-strain"))
    assert not plane_stress_model(make_regularizer("strain"))
    with pytest.raises(femreg.InputError, match="fine_maxiter_stress"):
        dataclasses.replace(DEEP_REFINEMENT, fine_maxiter_stress=0)
