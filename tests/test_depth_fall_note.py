"""An echo that weakens with depth (a recording without time-gain compensation): eq:objf weighs one alpha against
the average echo's image term, so the deep, weak echo is regularised more; register says so in its message
(femreg.image.depth_fall_note) where the echo's straight-line depth trend falls by more than
femreg.image.LEVEL_FALL_DB."""
import warnings

import numpy as np
import pytest

import femreg
from femreg.image import LEVEL_FALL_DB, depth_fall_note, depth_trend_db
from forward import fields as F
from forward.pairs import make_pair


@pytest.fixture(scope="module")
def pair():
    return make_pair(F.compression(0.01), "L7", (20.0, 15.0), 30.0, seed=4, top_mm=3.0)


def _ramp(img, fall_db):
    return img * 10.0 ** (-np.linspace(0.0, fall_db, img.shape[0]) / 20.0)[:, None]


def test_trend_reads_an_exponential_fall(pair):
    flat = depth_trend_db(pair.ref, pair.spacing)
    falls = [float(t[0] - t[-1]) for t in (flat, depth_trend_db(_ramp(pair.ref, 20.0), pair.spacing))]
    # speckle of even echogenicity: within 2 dB of flat; a 20 dB ramp read within 2 dB of it
    assert abs(falls[0]) < 2.0
    assert abs(falls[1] - (20.0 + falls[0])) < 2.0
    assert depth_fall_note(pair.ref, pair.spacing) == []
    note = depth_fall_note(_ramp(pair.ref, 25.0), pair.spacing)
    assert len(note) == 1 and "weakens 2" in note[0] and "time-gain compensation" in note[0]


def test_register_says_so_only_where_the_echo_falls(pair):
    kw = dict(spacing=pair.spacing, origin=pair.origin, refine=None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = femreg.register(pair.ref, pair.mov, **kw)
        ramped = femreg.register(_ramp(pair.ref, 25.0), _ramp(pair.mov, 25.0), **kw)
        slight = femreg.register(_ramp(pair.ref, LEVEL_FALL_DB - 4), _ramp(pair.mov, LEVEL_FALL_DB - 4), **kw)
    assert "weakens" not in plain.message and "weakens" not in slight.message
    assert ramped.success and "the echo weakens" in ramped.message, ramped.message
