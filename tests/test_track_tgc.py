"""femreg.track and femreg.elastogram on a loop whose receiver noise a time-gain compensation lifts to the echo's
level at depth: the level detection cuts nothing, and the loop is cut where frames 0 and 1 do not match after the
default start's block matching, as femreg.register cuts a pair (femreg.registration.noise_at_depth,
femreg.echo.unmatched_crop).

The loop: 12 MHz (L12), 20 x 12 mm, SNR 30 dB at the face, the echo meeting the noise at 15 mm, TGC flat to the
bottom; uniform axial compression of 1 % per frame, 3 frames.  Measured: before, track meshed the noise (3690
elements), both frames flagged (NCC after 0.34; frame 2 failed, read as envelope data), 62.9 / 29.4 % total strain
error over the echo; now cut at 13.2 mm, 210 elements, 2.18 / 0.68 % (the loop cut by hand at 15 mm: 399 elements,
5.73 / 1.11 %, its last 1.8 mm at an echo SNR of 0-3.6 dB).  The elastogram registered rows 0-1558, now 0-877."""
import warnings

import numpy as np
import pytest

import femreg
from femreg.elastogram import elastogram
from femreg.echo import find_echo
from femreg.registration import noise_at_depth
from forward import fields as F
from forward.pairs import PROBES, alpha_for_floor, attenuation_gain_db, box_points, make_sequence, total_strain_error

SNR, TOP, FLOOR = 30.0, 2.0, 15.0
#: Strain error over the echo, the loop as given minus the loop cut by hand at the floor: measured -3.55 / -0.43
#: points (frames 1 / 2); bound 0.5 points, the tolerance of the single pairs (tests/test_echo.py STRAIN_TOL_POINTS).
STRAIN_TOL_POINTS = 0.5


@pytest.fixture(scope="module")
def loop():
    pr = PROBES["L12"]
    gain = attenuation_gain_db(alpha_for_floor(FLOOR, SNR, pr.f0_mhz), pr.f0_mhz)
    return make_sequence(F.compression(0.01), "L12", (20.0, 12.0), SNR, 0, n_frames=3, step=0.01, top_mm=TOP,
                         echo_gain_db=gain, tgc_db=lambda x: -gain(x))


def _error(res, s, k, box, step=2):
    """Total strain error (%, e_xy weighted 2) of frame 0 -> k inside ``box`` (x0, x1, y0, y1) mm."""
    P = box_points(s.frames.shape[1:], s.spacing, s.origin, box, step)
    e, est = s.true_strain(k, P), res.strain(P)
    assert np.isfinite(est).all()
    return total_strain_error(est, e)


def test_track_cuts_the_noise_as_register_cuts_the_first_pair(loop):
    s = loop
    assert find_echo(s.frames[0], s.frames[1], spacing=s.spacing, origin=s.origin).full     # level: no cut
    n = int(round((FLOOR - s.origin[0]) / s.spacing[0])) + 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        seq = femreg.track(s.frames, spacing=s.spacing, origin=s.origin)
        hand = femreg.track(s.frames[:, :n], spacing=s.spacing, origin=s.origin, roi=None)
        pair = femreg.register(s.frames[0], s.frames[1], spacing=s.spacing, origin=s.origin)
    assert seq.flags == ["", ""] and all(r.success for r in seq), [r.message for r in seq]
    # register's cut of frames 0 and 1, said in every result; measured 13.2 mm (the floor 15 mm), bound as
    # tests/test_echo.py's: 2.5 mm above, 4 mm below
    assert pair.excluded and "the frames do not match there" in pair.excluded
    for r in seq:
        assert r.excluded == pair.excluded and r.roi == pair.roi and r.shape == s.frames[0].shape
        assert r.mesh.p[0].max() <= r.roi[1] + 1e-9
        assert np.isnan(r.on_grid()["exx"][-1]).all()
    assert FLOOR - 2.5 <= seq[0].roi[1] <= FLOOR + 4.0, seq[0].roi
    # the mesh sized on the echo (measured 210 elements, the hand cut's 399; before 3690 on the noise)
    assert seq[0].mesh.t.shape[1] <= 1.5 * hand[0].mesh.t.shape[1]
    box = (max(seq[0].mesh.p[0].min(), hand[0].mesh.p[0].min()), FLOOR - 3.0,
           hand[0].mesh.p[1].min(), hand[0].mesh.p[1].max())
    for k in (1, 2):
        assert _error(seq[k - 1], s, k, box) - _error(hand[k - 1], s, k, box) < STRAIN_TOL_POINTS


def test_elastogram_cuts_the_noise_as_register_cuts_the_first_pair(loop):
    s = loop
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = elastogram(s.frames, spacing=s.spacing, origin=s.origin)
    crop = noise_at_depth(s.frames[0], s.frames[1], spacing=s.spacing, origin=s.origin)
    assert crop is not None and res.excluded == crop.region.excluded
    (r0, r1), (c0, c1) = res.region
    assert (r0, r1) == (crop.slices[0].start, crop.slices[0].stop) and (c0, c1) == (0, s.frames.shape[2])
    # measured: rows 0-877 (13.2 mm); before 0-1558, the whole frames
    assert FLOOR - 2.5 <= s.origin[0] + r1 * s.spacing[0] <= FLOOR + 4.0
    assert res.exx.shape == (r1 - r0, c1 - c0)
    assert sum(bool(r["usable"]) for r in res.pairs) == 2


def test_no_cut_where_the_user_fixed_the_region_or_the_frames_match(loop):
    s = loop
    a, b = s.frames[0], s.frames[1]
    kw = dict(spacing=s.spacing, origin=s.origin)
    assert noise_at_depth(a, b, **kw) is not None
    # as register: a given roi, depth, mesh or data_mask fixes the region (nothing computed)
    assert noise_at_depth(a, b, roi=None, **kw) is None
    assert noise_at_depth(a, b, depth=(3.0, 18.0), **kw) is None
    assert noise_at_depth(a, b, roi=(3.0, 18.0, -5.0, 5.0), **kw) is None
    assert noise_at_depth(a, b, mesh=femreg.mesh.roi_mesh(a.shape, s.spacing, s.origin), **kw) is None
    assert noise_at_depth(a, b, data_mask=np.ones(a.shape, bool), **kw) is None
    with pytest.raises(femreg.errors.InputError, match="unknown keyword"):
        noise_at_depth(a, b, rio=None, **kw)
    # the same loop without the TGC's noise at depth (the SNR of the face everywhere): nothing cut
    clean = make_sequence(F.compression(0.01), "L12", (20.0, 12.0), SNR, 0, n_frames=2, step=0.01, top_mm=TOP)
    assert noise_at_depth(clean.frames[0], clean.frames[1], **kw) is None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        given = femreg.track(s.frames[:2], roi=None, **kw)
    assert given[0].excluded is None


def test_cli_track_says_what_was_cut_and_resumes(loop, tmp_path, capsys):
    import json

    from femreg.cli import main

    s = loop
    f = tmp_path / "loop.npz"
    np.savez(f, rf=s.frames, spacing=np.array(s.spacing), origin=np.array(s.origin))
    out = tmp_path / "run"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        assert main(["track", str(f), "-o", str(out), "--no-progress"]) == 0
        text = capsys.readouterr().out
        assert "left out of the mesh (the rest is registered): depth below" in text, text
        assert "the frames do not match there" in text
        region = json.loads((out / "track.json").read_text())["registered_region"]
        assert region["rows"][0] == 0 and region["rows"][1] < s.frames.shape[1]
        assert femreg.load_result(out / "frame_002.npz").excluded.startswith("depth below")
        # the crop is found again on resume: the run's parameters match, the frames are loaded
        (out / "frame_002.npz").unlink()
        assert main(["track", str(f), "-o", str(out), "--resume", "--no-progress"]) == 0
    assert femreg.load_result(out / "frame_002.npz").roi == femreg.load_result(out / "frame_001.npz").roi
