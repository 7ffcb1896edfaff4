"""Where the echo is in a volume (femreg.echo_volume): a noise floor below depth D, dead lateral lines and
elevational planes, saturated slabs found; the box registered, the full voxel grid kept (NaN outside), the box
saved; given boxes and depth ranges, a box outside the volume refused naming its extent; volumes with echo
everywhere registered exactly as before; track and the command line."""
import numpy as np
import pytest

import femreg
from femreg.echo_volume import crop_for_volume, find_echo_volume
from femreg.errors import InputError
from femreg.volume_result import load_volume_result
from forward.pairs import alpha_for_floor, attenuation_gain_db
from forward.volume import VOLUME_PROBES, Affine3D, make_volume_pair

TOP, SNR = 2.0, 30.0
#: Detected depth against the truth (echo power = noise power): measured -0.14 .. +0.27 mm over matrix7 / swept3 /
#: matrix12 x floor at 40 / 60 % of 20 mm (benchmarks/volume_echo.py, seed 0), -0.64 .. +0.64 mm on seed 1 at
#: 15 x 10 and 8 x 6 mm apertures except the 3.5 MHz probe on 8 x 6 mm (+1.18 / +1.42 mm: 16 x 12 lines of a 2.2 x
#: 3 mm beam); at 80 % (4 mm of floor) -0.04 .. -1.50 mm.  The 2D target, 1 mm, is the bound on the cases inside it.
DEPTH_TOL_MM = 1.0


def floor_volume(probe="swept3", size=(12.0, 10.0, 8.0), frac=0.6, seed=0, field=None):
    f0 = VOLUME_PROBES[probe].f0_mhz
    depth = TOP + frac * size[0]
    gain = attenuation_gain_db(alpha_for_floor(depth, SNR, f0), f0)
    pair = make_volume_pair(field or Affine3D(0.01), probe, size, seed=seed, top_mm=TOP, snr_db=SNR,
                            echo_gain_db=gain)
    return pair, depth


@pytest.fixture(scope="module")
def floor_pair():
    return floor_volume()


@pytest.mark.parametrize("probe,size,frac", [("swept3", (20.0, 15.0, 10.0), 0.4), ("matrix7", (20.0, 8.0, 6.0), 0.6)])
def test_noise_floor_depth_found(probe, size, frac):
    # seed 1: not the benchmark's volumes; measured +0.57 / -0.64 mm here
    pair, depth = floor_volume(probe, size, frac, seed=1)
    box = find_echo_volume(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin)
    assert abs(box.roi_mm[1] - depth) < DEPTH_TOL_MM, (box.roi_mm, depth)
    assert box.ranges[1:] == ((0, pair.ref.shape[1]), (0, pair.ref.shape[2]))     # every line and plane has echo
    assert "depth below" in box.excluded and "noise floor" in box.excluded
    # without attenuation the same volume has no floor: nothing is excluded
    flat = make_volume_pair(Affine3D(0.01), probe, size, seed=1, top_mm=TOP, snr_db=SNR)
    assert find_echo_volume(flat.ref, flat.mov, spacing=flat.spacing, origin=flat.origin).excluded is None


def test_dead_lines_planes_and_saturation_are_left_out(floor_pair):
    pair, _ = floor_pair
    ref, mov = pair.ref.astype(float), pair.mov.astype(float)
    for v in (ref, mov):
        v[:, :2] = 0.0            # two dead lateral lines (left)
        v[:, :, -3:] = 0.0        # three dead elevational planes at the end of a sweep (back)
    box = find_echo_volume(ref, mov, spacing=pair.spacing, origin=pair.origin)
    assert box.ranges[1] == (2, ref.shape[1]) and box.ranges[2] == (0, ref.shape[2] - 3), box
    assert "lateral lines at" in box.excluded and "(left) excluded: no signal" in box.excluded
    assert "elevational planes at" in box.excluded and "(back) excluded: no signal" in box.excluded
    # the first 20 rows at the converter's limit
    sat = pair.ref.astype(float)
    sat[:20] = np.sign(sat[:20]) * np.max(np.abs(sat))
    box = find_echo_volume(sat, spacing=pair.spacing, origin=pair.origin)
    assert box.ranges[0][0] == 20 and "saturated" in box.excluded, box


def test_registered_inside_the_box_on_the_full_grid(floor_pair, tmp_path):
    pair, depth = floor_pair
    res = femreg.register(pair.ref, pair.mov, spacing=pair.spacing, origin=pair.origin)
    assert res.success, res.message
    assert res.excluded and "depth below" in res.excluded and res.excluded in res.message
    x0, x1 = res.roi[:2]
    assert abs(x1 - depth) < DEPTH_TOL_MM
    assert res.shape == pair.ref.shape and np.allclose(res.origin, pair.origin)
    g = res.on_grid()
    x = pair.grid.x
    assert g["exx"].shape == pair.ref.shape
    assert np.all(np.isnan(g["exx"][x > x1]))                       # nothing below the box
    inner = g["exx"][(x > x0 + 1.5) & (x < x1 - 1.5)][:, 3:-3, 3:-3]
    assert np.all(np.isfinite(inner))
    assert abs(np.median(inner) + 0.01) < 0.002                     # 1 % compression
    path = res.save(tmp_path / "r.npz")
    back = load_volume_result(path)
    assert back.excluded == res.excluded and back.roi == pytest.approx(res.roi)


def test_given_box_and_depth_and_boxes_outside(floor_pair):
    pair, _ = floor_pair
    sp, org, shape = pair.spacing, pair.origin, pair.ref.shape
    ext = pair.grid.extent()
    box = (4.0, 9.0, -3.0, 3.0, -2.5, 2.5)
    crop = crop_for_volume(pair.ref, pair.mov, sp, org, roi=box)
    assert crop.roi_mm[0] <= box[0] + sp[0] and crop.roi_mm[1] >= box[1] - sp[0]
    assert "outside the given roi" in crop.region.excluded
    crop = crop_for_volume(pair.ref, pair.mov, sp, org, depth=(4.0, 9.0))
    assert crop.region.ranges[1:] == ((0, shape[1]), (0, shape[2]))
    with pytest.raises(InputError, match=r"leaves the volume; the volume's extent is x \(axial\).*z \(elevational\)"):
        femreg.register(pair.ref, pair.mov, spacing=sp, origin=org, roi=(4.0, 9.0, -3.0, 3.0, 2.0, ext[5] + 5.0))
    with pytest.raises(InputError, match="extent"):
        femreg.register(pair.ref, pair.mov, spacing=sp, origin=org, depth=(ext[1] + 1.0, ext[1] + 5.0))
    with pytest.raises(InputError, match=r"\(x0, x1, y0, y1, z0, z1\)"):
        femreg.register(pair.ref, pair.mov, spacing=sp, origin=org, roi=(4.0, 9.0, -3.0, 3.0))
    with pytest.raises(InputError, match="user mesh"):
        from femreg.voxels import roi_mesh_3d

        femreg.register(pair.ref, pair.mov, spacing=sp, origin=org, roi=box, mesh=roi_mesh_3d(shape, sp, org))


def test_echo_everywhere_registers_exactly_as_before():
    pair = make_volume_pair(Affine3D(0.01), "swept3", (12.0, 8.0, 8.0), seed=1, snr_db=SNR)
    kw = dict(spacing=pair.spacing, origin=pair.origin)
    assert crop_for_volume(pair.ref, pair.mov, **kw) is None
    a = femreg.register(pair.ref, pair.mov, **kw)
    b = femreg.register(pair.ref, pair.mov, roi=None, **kw)
    assert a.excluded is None and a.roi is None
    assert np.array_equal(a.u, b.u)


def test_track_uses_one_box_for_every_volume(floor_pair):
    pair, depth = floor_pair
    box = (2.5, depth - 0.2, -4.5, 4.5, -3.5, 3.5)
    tr = femreg.track([pair.ref, pair.mov, pair.ref], spacing=pair.spacing, origin=pair.origin, roi=box)
    assert tr.success and len(tr) == 2
    for r in tr.accumulated + tr.results:
        assert r.roi == tr.accumulated[0].roi and r.shape == pair.ref.shape
        assert "outside the given roi" in r.excluded
    g = tr.accumulated[0].on_grid()
    x = pair.grid.x
    assert np.all(np.isnan(g["exx"][x > tr.accumulated[0].roi[1] + 1.0]))


def test_cli_roi_takes_six_numbers_for_a_volume(floor_pair, tmp_path, capsys):
    from femreg.cli import main

    pair, depth = floor_pair
    f = tmp_path / "vols.npz"
    np.savez(f, rf=pair.frames, spacing=np.asarray(pair.spacing), origin=np.asarray(pair.origin))
    out = tmp_path / "r.npz"
    box = ["3", f"{depth - 1.0:g}", "-3", "3", "-2", "2"]
    assert main(["register", str(f), "-o", str(out), "--roi", *box]) == 0
    res = load_volume_result(out)
    assert res.roi is not None and abs(res.roi[1] - (depth - 1.0)) <= pair.spacing[0]
    assert "left out of the mesh" in capsys.readouterr().out
    assert main(["register", str(f), "-o", str(out), "--roi", "3", "9", "-3", "3", "-2"]) == 2
    assert "--roi takes" in capsys.readouterr().err
    assert main(["register", str(f), "-o", str(out), "--depth", "3", "40"]) == 2
    assert "extent" in capsys.readouterr().err


def tgc_volumes(n_volumes=2, floor=12.0, seed=0):
    """A matrix7 sequence (16 x 10 x 8 mm from 2 mm, 1 % compression and 0.3 % shear e_xy per volume) whose echo
    sinks into the receiver noise at ``floor`` mm and a time-gain compensation lifts both back: the level is flat
    to the bottom (the level rule sees nothing)."""
    from forward.volume import make_volume_sequence

    f0 = VOLUME_PROBES["matrix7"].f0_mhz
    gain = attenuation_gain_db(alpha_for_floor(floor, SNR, f0), f0)
    fields = [Affine3D(0.01 * k, shear={"xy": 0.003 * k}) for k in range(1, n_volumes)]
    return make_volume_sequence(fields, "matrix7", (16.0, 10.0, 8.0), seed=seed, top_mm=TOP, snr_db=SNR,
                                echo_gain_db=gain, tgc_db=lambda x: -gain(x))


def _echo_error(res, seq, k=1, depth=(3.0, 9.0)):
    """Six-component total strain error (%, shears weighted 2) over the echo, 1 mm inside the sides."""
    g = seq.grid
    ax = [g.axis(a) for a in range(3)]
    ext = g.extent()
    X = np.meshgrid(ax[0][(ax[0] >= depth[0]) & (ax[0] <= depth[1])][::4],
                    ax[1][(ax[1] >= ext[2] + 1) & (ax[1] <= ext[3] - 1)],
                    ax[2][(ax[2] >= ext[4] + 1) & (ax[2] <= ext[5] - 1)], indexing="ij")
    P = np.column_stack([x.ravel() for x in X])
    est, true = res.strain(P), seq.true_strain(k, P)
    w = np.array([1, 1, 1, 2, 2, 2.0])
    return 100.0 * float(np.sqrt(np.sum(w * (est - true) ** 2) / np.sum(w * true ** 2)))


@pytest.fixture(scope="module")
def tgc_sequence():
    return tgc_volumes(3)


def test_noise_a_tgc_lifts_at_depth_is_cut(tgc_sequence):
    # the level is flat: the level rule keeps everything; the 2D rule on the block matching of the volumes' planes
    # (femreg.echo.unmatched_crop) cuts at 10.1 mm, 1.9 mm above the floor (seeds 0-2).  Measured (seeds 0 / 1 / 2):
    # total strain error over the echo (3-9 mm) 5.4 / 8.2 / 9.0 % cut, 34.8 / 77.8 / 101.2 % on the whole volumes
    # (the noise meshed, reported as success), 22.2 / 14.6 / 23.8 % cut by hand at the floor.
    seq = tgc_sequence
    ref, mov = seq.frames[0], seq.frames[1]
    assert find_echo_volume(ref, mov, spacing=seq.spacing, origin=seq.origin).excluded is None
    res = femreg.register(ref, mov, spacing=seq.spacing, origin=seq.origin)
    whole = femreg.register(ref, mov, spacing=seq.spacing, origin=seq.origin, roi=None)
    assert res.success and res.roi is not None and 9.0 < res.roi[1] < 12.0, res.roi
    assert "do not match there" in res.excluded and res.excluded in res.message
    assert res.shape == ref.shape and whole.excluded is None
    # bounds: 1.5 x the cut's 5.4 %; the whole volumes' 34.8 % is 6.4 x it
    err, err_whole = _echo_error(res, seq), _echo_error(whole, seq)
    assert err < 8.0 and err_whole > 3.0 * err, (err, err_whole)
    g = res.on_grid()
    assert np.all(np.isnan(g["exx"][seq.grid.x > res.roi[1] + 1.0]))


def test_track_cuts_the_loop_once_from_its_first_volumes(tgc_sequence):
    seq = tgc_sequence
    tr = femreg.track(seq.frames, spacing=seq.spacing, origin=seq.origin)
    one = femreg.register(seq.frames[0], seq.frames[1], spacing=seq.spacing, origin=seq.origin)
    assert len(tr) == 2
    for r in tr.accumulated + tr.results:
        assert r.roi == one.roi and "do not match there" in r.excluded
    # measured 5.4 % (frame 0 -> 1) and 5.1 % (0 -> 2), seed 0 (seed 1: 8.2 / 8.0 %); the whole loop 34.8 / 183 %
    # (0 -> 2 flagged); bound 1.5 x seed 0's
    errs = [_echo_error(r, seq, k + 1) for k, r in enumerate(tr.accumulated)]
    assert max(errs) < 8.0, errs


def test_info_names_the_carrier_above_the_noise(tgc_sequence, tmp_path, capsys):
    # the whole depth of the central plane reads no carrier (its deepest quarter is broadband noise at the echo's
    # level): before, "no RF carrier along axis 0 ...: envelope or B-mode data"
    from femreg.cli import main
    from femreg.orientation import CARRIER_RATIO, axial_carrier_ratio

    seq = tgc_sequence
    plane = seq.frames[0][:, :, seq.frames[0].shape[2] // 2]
    assert axial_carrier_ratio(plane) > CARRIER_RATIO
    f = tmp_path / "vols.npz"
    np.savez(f, rf=np.asarray(seq.frames), spacing=np.asarray(seq.spacing), origin=np.asarray(seq.origin))
    assert main(["info", str(f)]) == 0
    line = next(s for s in capsys.readouterr().out.splitlines() if s.startswith("RF"))
    assert "RF carrier along axis 0" in line and "broadband" in line and "envelope" not in line, line
    assert "7.0" in line.split("MHz")[0][-6:], line      # the 7 MHz probe's carrier
