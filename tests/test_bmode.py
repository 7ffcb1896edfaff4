"""Envelope / B-mode frames (no RF carrier): registered on the envelope, without the RF-period peak-hopping check
(no period to hop by), and said so in the result."""
from __future__ import annotations

import numpy as np
import pytest

import femreg
from forward.display import bmode_uint8, sector_fan


def _bmode(rf):
    """Log-compressed 8-bit B-mode (50 dB), as a scanner's video output stores it."""
    return bmode_uint8(rf)


@pytest.fixture(scope="module")
def pair():
    from forward import fields as F
    from forward.pairs import make_pair

    return make_pair(F.compression(0.01), probe="paper", size_mm=(24.0, 18.0), snr_db=20.0, seed=5)


def test_bmode_pair_registers_with_a_note(pair):
    a, b = _bmode(pair.ref), _bmode(pair.mov)
    r = femreg.register(a, b, spacing=pair.spacing, origin=pair.origin)
    assert r.success, r.message
    assert "envelope / B-mode data" in r.message and "peak-hopping" in r.message
    pts = r.pixel_points()[::5]
    e = r.strain(pts)
    t = pair.field.strain(pts)
    ok = np.isfinite(e).all(1)
    err = np.linalg.norm(e[ok, :2] - t[ok, :2]) / np.linalg.norm(t[ok, :2])
    # measured 0.017 (the RF pair: 0.003); before, the RF-period hop check failed such pairs or the never-worse
    # rule returned the block-matching start (robustness pair comp1_paper as B-mode: FAILED, 3.7 % -> 0.6 %)
    assert err < 0.05, err
    assert r.hop_gain is None


def test_rf_pair_keeps_the_hop_check(pair):
    r = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin)
    assert r.success and "envelope" not in r.message and r.hop_gain is not None


def _inclusion_bmode_pair():
    """A stiff disk (x4, r 3 mm at 20 mm depth, plane strain) under 2 % compression, L7, 30 dB."""
    from forward import fields as F
    from forward.pairs import make_pair

    field = F.Inclusion("stiff", "plane-strain", 0.02, radius_mm=3.0)
    return make_pair(field, "L7", (16.0, 14.0), 30.0, 2, top_mm=12.0)


def test_display_levels_register_as_their_speckle_not_their_mean():
    """The data term is normalised by each frame's mean and spread: the same B-mode as display grey levels
    (mean ~200), shifted and scaled, registers to the same field; divided by its RMS instead, its speckle kept 0.1
    of unit scale and the default alpha flattened the disk (strain error 9.6 % on a scan-converted L12 loop,
    the error of a uniform field), and an offset changed the result."""
    p = _inclusion_bmode_pair()
    a, b = _bmode(p.ref).astype(float), _bmode(p.mov).astype(float)
    r = femreg.register(a, b, spacing=p.spacing, origin=p.origin)
    s = femreg.register(3.0 * a - 400.0, 3.0 * b - 400.0, spacing=p.spacing, origin=p.origin)
    pts = r.pixel_points()[::7]
    assert np.nanmax(np.abs(r.displacement(pts) - s.displacement(pts))) < 1e-6
    e, t = r.strain(pts)[:, 0], p.field.strain(pts)[:, 0]
    ok = np.isfinite(e)
    err = np.sqrt(np.mean((e[ok] - t[ok]) ** 2)) / np.mean(np.abs(t[ok]))
    flat = np.sqrt(np.mean((np.mean(t[ok]) - t[ok]) ** 2)) / np.mean(np.abs(t[ok]))
    # measured 14.6 % (RMS-normalised as before: 16.5 %; the RF pair 11.6 %; a uniform field 27.5 %): bound 15.5 %
    assert err < 0.155 and err < 0.6 * flat, (err, flat)


def test_bmode_picture_of_display_levels_keeps_their_contrast(pair):
    """femreg.plot.bmode of frames already log-compressed (display grey levels) maps them linearly; compressing
    them again put every pixel within 3 dB of the maximum (a white picture)."""
    from femreg.plot import bmode

    img = bmode(_bmode(pair.ref), 50.0)
    assert np.percentile(img, 95) - np.percentile(img, 5) > 20.0
    from femreg.speckle import envelope

    env = envelope(pair.ref)
    np.testing.assert_allclose(bmode(env, 50.0), bmode(pair.ref, 50.0), atol=1e-9)   # an envelope: its amplitude


_fan = sector_fan          # a scan-converted sector's footprint


def test_scan_converted_sector_registers_the_whole_fan(tmp_path):
    """A B-mode pair inside a fan with black wedges (a convex probe's scan-converted image): the wedges are fixed
    on the screen while the tissue moves; registered whole they pulled the displacement to zero (a fan-masked L12
    loop: 78 % strain error, FAILED).  The fill is found, the mesh spans the fan's bounding box, eq:IR leaves the
    fill and its neighbourhood out (femreg.echo.fan_weights), the pyramid starts on the largest rectangle without
    fill, and nothing is reported outside the fan."""
    p = _inclusion_bmode_pair()
    fan = _fan(p.ref.shape, p.spacing, p.origin)
    a, b = (np.where(fan, _bmode(f), 0).astype(np.uint8) for f in (p.ref, p.mov))
    r = femreg.register(a, b, spacing=p.spacing, origin=p.origin)
    assert r.success and "fill of value 0" in r.message and "NaN outside the fan" in r.message, r.message
    pts = r.pixel_points()
    e = r.strain(pts)[:, 0]
    ok = np.isfinite(e)
    assert not np.any(ok & ~fan.ravel())                  # nothing reported outside the fan
    assert np.all(np.isnan(r.on_grid()["exx"][~fan]))
    t = p.field.strain(pts[ok])[:, 0]
    err = np.sqrt(np.mean((e[ok] - t) ** 2)) / np.mean(np.abs(t))
    cover = ok.sum() / fan.sum()
    # measured 20.7 % on 85 % of the fan (the rest: the mesh margin); on its largest rectangle alone (before)
    # 24.5 % on 48 %, the pair without the fan 15.4 %; the pyramid on the whole fan: 146 %, FAILED.  Bounds: 23 %
    # and 80 %
    assert err < 0.23 and cover > 0.80, (err, cover)
    # saved and read back, the result still reports nothing outside the fan
    r.save(tmp_path / "fan.npz")
    back = femreg.load_result(tmp_path / "fan.npz")
    np.testing.assert_array_equal(back.data_mask, fan)
    assert not np.any(np.isfinite(back.strain(pts)[:, 0]) & ~fan.ravel())


def test_largest_rectangle_against_brute_force():
    from femreg.echo import _largest_rectangle

    rng = np.random.default_rng(4)
    for _ in range(20):
        mask = rng.random((9, 11)) > 0.25
        (r0, r1), (c0, c1) = _largest_rectangle(mask)
        assert mask[r0:r1, c0:c1].all()
        best = max(((i1 - i0) * (j1 - j0) for i0 in range(9) for i1 in range(i0 + 1, 10)
                    for j0 in range(11) for j1 in range(j0 + 1, 12) if mask[i0:i1, j0:j1].all()), default=0)
        assert (r1 - r0) * (c1 - c0) == best


def test_fill_is_black_fill_touching_the_edge_only(pair):
    """find_fill: black wedges are fill; a saturated bright layer across the image and black speckle inside the
    tissue are not."""
    from femreg.echo import find_fill

    a, b = _bmode(pair.ref), _bmode(pair.mov)
    bright_a, bright_b = a.copy(), b.copy()
    bright_a[300:400], bright_b[300:400] = 255, 255            # 8 % of the frame, touching both sides
    assert find_fill(bright_a, bright_b, pair.spacing, pair.origin) is None
    assert np.mean(a == 0) > 0 and find_fill(a, b, pair.spacing, pair.origin) is None   # clipped speckle
    fan = _fan(a.shape, pair.spacing, pair.origin)
    r = find_fill(np.where(fan, a, 0), np.where(fan, b, 0), pair.spacing, pair.origin)
    (r0, r1), (c0, c1) = r.rows, r.cols
    assert fan[r0:r1, c0:c1].all() and (r1 - r0) * (c1 - c0) > 0.3 * fan.sum()


def test_info_names_the_fill_it_will_leave_out(pair, tmp_path, capsys):
    from femreg.cli import main

    fan = _fan(pair.ref.shape, pair.spacing, pair.origin)
    frames = np.stack([np.where(fan, _bmode(f), 0) for f in (pair.ref, pair.mov)]).astype(np.uint8)
    path = tmp_path / "fan.npz"
    np.savez(path, frames=frames, spacing=np.asarray(pair.spacing), origin=np.asarray(pair.origin))
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "fill      fill of value 0" in out and "NaN outside the fan" in out and "elastogram" in out, out


def test_track_keeps_the_whole_fan_too():
    """femreg.track on the fan pair: the fill weighted 0 in every pair, results NaN outside the fan.  Measured
    18.5 % on 85 % of the fan (register: 20.7 %; the largest rectangle: 24.5 % on 48 %): bounds 21 % and 80 %."""
    p = _inclusion_bmode_pair()
    fan = _fan(p.ref.shape, p.spacing, p.origin)
    a, b = (np.where(fan, _bmode(f), 0).astype(np.uint8) for f in (p.ref, p.mov))
    res = femreg.track(np.stack([a, b]), spacing=p.spacing, origin=p.origin)[-1]
    assert res.success, res.message
    pts = res.pixel_points()
    e = res.strain(pts)[:, 0]
    ok = np.isfinite(e)
    assert not np.any(ok & ~fan.ravel()) and not np.any(np.isfinite(res.on_grid()["exx"]) & ~fan)
    t = p.field.strain(pts[ok])[:, 0]
    err = np.sqrt(np.mean((e[ok] - t) ** 2)) / np.mean(np.abs(t))
    assert err < 0.21 and ok.sum() > 0.8 * fan.sum(), (err, ok.sum() / fan.sum())


def _fan_bmode_pair():
    """The inclusion pair as 8-bit B-mode inside the fan of :func:`_fan` (wedges 0), and the fan."""
    p = _inclusion_bmode_pair()
    fan = _fan(p.ref.shape, p.spacing, p.origin)
    a, b = (np.where(fan, _bmode(f), 0).astype(np.uint8) for f in (p.ref, p.mov))
    return p, fan, a, b


def _fan_score(r, mask, field):
    """(axial strain error, fraction of ``mask`` with a finite strain, finite pixels outside ``mask``)."""
    pts = r.pixel_points()
    e = r.strain(pts)[:, 0]
    ok = np.isfinite(e)
    t = field.strain(pts[ok])[:, 0]
    return (np.sqrt(np.mean((e[ok] - t) ** 2)) / np.mean(np.abs(t)), ok.sum() / mask.sum(),
            int(np.sum(ok & ~mask.ravel())))


def test_data_mask_given_explicitly():
    """``data_mask=`` replaces the detection of the fill.  The detected fan given as the mask gives the very
    result of ``data_mask=None`` (the detection); a narrower mask (the fan below 30 % of the depth) is cut to,
    left out of eq:IR outside and reported: NaN outside it, ``result.data_mask`` the mask, the message naming it;
    on frames not cut to it (``roi=None``) as well.  Measured: 20.5 % on 79 % of the mask (cut), 23.3 % on 86 %
    (not cut); the detection 20.7 % on 85 % of the fan.  Bounds 23 / 26 % and 70 / 78 %."""
    from femreg.echo import find_fill

    p, fan, a, b = _fan_bmode_pair()
    kw = dict(spacing=p.spacing, origin=p.origin)
    auto = femreg.register(a, b, **kw)
    detected = ~find_fill(a.astype(float), b.astype(float), p.spacing, p.origin).fill
    given = femreg.register(a, b, data_mask=detected, **kw)
    np.testing.assert_array_equal(given.u, auto.u)
    np.testing.assert_array_equal(given.data_mask, auto.data_mask)
    part = fan & (np.arange(fan.shape[0])[:, None] >= int(0.3 * fan.shape[0]))
    for extra, bound, cover in ((dict(), 0.23, 0.70), (dict(roi=None), 0.26, 0.78)):
        r = femreg.register(a, b, data_mask=part, **kw, **extra)
        assert r.success, r.message
        np.testing.assert_array_equal(r.data_mask, part)
        err, frac, outside = _fan_score(r, part, p.field)
        assert outside == 0 and np.all(np.isnan(r.on_grid()["exx"][~part]))
        assert err < bound and frac > cover, (extra, err, frac)
    assert "outside the given data_mask" in femreg.register(a, b, data_mask=part, **kw).message
    res = femreg.track(np.stack([a, b]), data_mask=part, **kw)[-1]       # every pair of a track too
    np.testing.assert_array_equal(res.data_mask, part)
    assert not np.any(np.isfinite(res.on_grid()["exx"]) & ~part)


def test_data_mask_refused_where_it_cannot_apply():
    from femreg.errors import InputError

    p, fan, a, b = _fan_bmode_pair()
    kw = dict(spacing=p.spacing, origin=p.origin)
    for bad in (fan.astype(np.uint8), fan[:-1], np.zeros_like(fan)):     # not bool, not the frames' shape, empty
        with pytest.raises(InputError, match="data_mask"):
            femreg.register(a, b, data_mask=bad, **kw)
    with pytest.raises(InputError, match="data_mask or roi"):
        femreg.register(a, b, data_mask=fan, roi=(5.0, 15.0, -3.0, 3.0), **kw)
    with pytest.raises(InputError, match="convex / sector"):
        femreg.register(a, b, data_mask=fan, geometry=femreg.Convex(), spacing=0.1)
    with pytest.raises(InputError, match="volumes"):
        femreg.register(np.ones((8, 8, 8)), np.ones((8, 8, 8)), spacing=1.0, data_mask=np.ones((8, 8), bool))
