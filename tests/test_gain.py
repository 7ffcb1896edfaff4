"""Gain and amplitude: frames of different gain or sample type register as matched ones (per-frame RMS
normalisation, femreg.image); blank and saturated frames are input errors naming the cause."""
import numpy as np
import pytest

import femreg
from femreg.errors import InputError
from femreg.metrics import field_errors
from forward.freehand import FreehandTissue
from forward.pairs import make_pair

TISSUE = FreehandTissue(inclusion_depth_mm=11.0, inclusion_radius_mm=3.0)


class _Field:
    """1 % compression with a stiff inclusion (forward.freehand's tissue model)."""
    name = "inclusion 1 %"

    def displacement(self, p):
        return 0.01 * TISSUE.U(p)

    def strain(self, p):
        G = 0.01 * TISSUE.grad_U(p)
        return np.column_stack([G[:, 0, 0], G[:, 1, 1], 0.5 * (G[:, 0, 1] + G[:, 1, 0])])


@pytest.fixture(scope="module")
def pair():
    return make_pair(_Field(), probe="paper", size_mm=(20.0, 15.0), seed=1)


def _err(p, ref, mov):
    r = femreg.register(ref, mov, spacing=p.spacing, origin=p.origin)
    assert r.success, r.message
    return 100 * field_errors(r, p.true_displacement, p.true_strain)["e"]


def test_gain_changes_register_as_matched_gain(pair):
    base = _err(pair, pair.ref, pair.mov)
    assert base < 15.0
    for g in (0.3, 0.9, 1.1, 3.0):
        # target: within 0.3 points of matched gain (measured: equal to 0.01 points; with the reference's RMS
        # for both images, 0.9 cost 2.6 points)
        assert abs(_err(pair, pair.ref, g * pair.mov) - base) <= 0.3, g


def test_integer_counts_register_as_float(pair):
    base = _err(pair, pair.ref, pair.mov)
    scale = 20000.0 / np.abs(pair.ref).max()
    q = [np.round(f * scale).astype(np.int16) for f in (pair.ref, pair.mov)]
    assert abs(_err(pair, *q) - base) <= 0.3
    # float reference against int16 counts x1000 of the moving frame
    assert abs(_err(pair, pair.ref, np.round(pair.mov * 1000).astype(np.int16)) - base) <= 0.3


def test_frame_against_itself_scaled_finds_zero_motion(pair):
    r = femreg.register(pair.ref, 3.0 * pair.ref, spacing=pair.spacing, origin=pair.origin)
    assert r.success, r.message
    assert np.max(np.abs(r.u)) < 1e-6


def test_blank_and_saturated_frames_are_input_errors(pair):
    with pytest.raises(InputError, match="all zero"):
        femreg.register(pair.ref, np.zeros_like(pair.ref), spacing=pair.spacing)
    top = 0.01 * np.abs(pair.mov).max()
    with pytest.raises(InputError, match="saturated"):
        femreg.register(pair.ref, np.clip(pair.mov, -top, top), spacing=pair.spacing)
    # a few clipped samples are not saturation
    top = 0.9 * np.abs(pair.mov).max()
    femreg.register(pair.ref, np.clip(pair.mov, -top, top), spacing=pair.spacing, maxiter=1)
