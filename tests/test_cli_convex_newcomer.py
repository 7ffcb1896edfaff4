"""A convex-probe recording as a scanner exports it (MATLAB struct header: Hz, m/s, metres, degrees; int16
(samples, lines, frames)), and the same frames scan-converted onto a Cartesian grid with zero wedges around the
fan: what a first-time user meets on the command line."""
from __future__ import annotations

import textwrap

import numpy as np
import pytest

scipy_io = pytest.importorskip("scipy.io")

R_MM, PITCH_DEG = 40.0, 0.6


def _cli(argv, capsys):
    from femreg.cli import main

    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def pair():
    from femreg import Convex
    from forward import fields as F
    from forward.beam import make_beam_pair

    return make_beam_pair(F.compression(0.01), Convex(radius_mm=R_MM, angle_pitch_deg=PITCH_DEG), probe="L7",
                          depth_mm=12.0, n_rays=40, snr_db=30.0, seed=1)


def _rf(p):
    """(samples, lines, frames) int16, as a scanner's MATLAB export."""
    return np.round(np.stack([p.ref, p.mov], axis=-1) * 1000).astype(np.int16)


@pytest.fixture(scope="module")
def files(pair, tmp_path_factory):
    p = pair
    d = tmp_path_factory.mktemp("convex_mat")
    fs = 1540.0 / (2.0 * p.spacing[0] * 1e-3)
    head = dict(sampling_frequency=fs, sound_speed=1540.0, probe_radius=R_MM * 1e-3, center_frequency=7.5e6)
    scipy_io.savemat(d / "step.mat", dict(RFdata=_rf(p), header=dict(head, line_angle_step=PITCH_DEG)))
    scipy_io.savemat(d / "angles.mat", dict(RFdata=_rf(p), header=dict(head, line_angles=p.geometry.angles(40))))
    scipy_io.savemat(d / "bare.mat", dict(RFdata=_rf(p)))
    return d


def test_angle_step_names():
    from femreg.io.checks import geometry_fields

    for name in ("line_angle_step", "rayAngleIncrement", "beam_angle_spacing_deg", "d_line_angle"):
        assert geometry_fields({name: 0.3})["angle_pitch_deg"] == pytest.approx(0.3), name
    assert geometry_fields({"line_angle_step_rad": 0.005236})["angle_pitch_deg"] == pytest.approx(0.3, rel=1e-3)
    # a linear array's plane-wave steering step is no ray pitch: such a file stays registrable as linear
    assert geometry_fields({"angle_step": 1.0}) == {} and geometry_fields({"theta_increment": 0.5}) == {}


def test_header_struct_names_the_probe(files, capsys):
    """``header.line_angle_step`` (deg) and ``header.probe_radius`` (m), or a vector ``header.line_angles``
    (rad) inside the struct: info names the flags.  Before: neither was recognised, info suggested a lateral
    line pitch, and elastogram ran the fan as a linear array's lines (exit 0); now it refuses without
    --geometry, naming the flags it takes."""
    for name in ("step.mat", "angles.mat"):
        rc, out, err = _cli(["info", files / name], capsys)
        assert rc == 1 and "--geometry convex --radius 40 --angle-pitch 0.6" in out, out
        assert "auto" in out                                # no lateral pitch asked for
    rc, out, err = _cli(["elastogram", files / "step.mat", "--spacing", 0.01925, 0.2, "-o", files / "el"], capsys)
    assert rc == 2 and "--geometry convex --radius 40 --angle-pitch 0.6" in err and "--geometry linear" in err, err


def test_radius_in_centimetres_is_caught(files, pair, tmp_path, capsys):
    """--radius 4 typed in cm: refused against the header's 40 mm (before: exit 0, a wrong fan, 49 % total strain
    error on a 60 mm deep abdominal loop); without a header a note; --radius 0.04 (metres) refused."""
    dr = pair.spacing[0]
    base = ["--geometry", "convex", "--angle-pitch", PITCH_DEG, "--spacing", dr, "auto", "--origin", 3, 0]
    rc, out, err = _cli(["register", files / "step.mat", "--radius", 4, *base, "-o", tmp_path / "a.npz"], capsys)
    assert rc == 2 and "--radius 4 mm against 40 mm" in err and "Traceback" not in err, err
    assert not (tmp_path / "a.npz").exists()
    rc, out, err = _cli(["register", files / "bare.mat", "--radius", 0.04, *base, "-o", tmp_path / "b.npz"], capsys)
    assert rc == 2 and "in metres it would be --radius 40" in err, err
    rc, out, err = _cli(["register", files / "bare.mat", "--radius", 4, *base, "--maxiter", 1,
                         "-o", tmp_path / "c.npz"], capsys)
    assert rc in (0, 1) and "in centimetres it would be --radius 40" in err, err


def test_geometry_flags_on_a_command_without_them(files, tmp_path, capsys):
    """Before: 'unrecognized arguments: --geometry convex ... (after -o: femreg elastogram --help gives how many
    values it takes)', which points at -o."""
    rc, out, err = _cli(["measure", files / "step.mat", "--inclusion", 4, 0, 1, "--geometry", "convex"], capsys)
    assert rc == 2 and "has no --geometry option" in err and "stored in the result" in err, err
    assert "after" not in err, err
    rc, out, err = _cli(["info", files / "step.mat", "--bogus"], capsys)
    assert rc == 2 and "femreg info has no --bogus option" in err, err


def test_transposed_convex_frames_keep_the_range_step(files, pair, tmp_path, capsys):
    """The spacing to keep is the range step with 'auto', not the rays' distance at the middle sample (before:
    'keep --spacing 0.0192 0.44...', a lateral value the user never gave)."""
    dr = pair.spacing[0]
    rc, out, err = _cli(["register", files / "step.mat", "--transpose", "--geometry", "convex", "--radius", R_MM,
                         "--angle-pitch", PITCH_DEG, "--spacing", dr, "auto", "-o", tmp_path / "t.npz"], capsys)
    assert rc == 2 and "transposed" in err and f"--spacing {dr:g} auto" in err, err


@pytest.fixture(scope="module")
def registered(files, pair, tmp_path_factory):
    from femreg.cli import main

    out = tmp_path_factory.mktemp("convex_res") / "p.npz"
    rc = main([str(a) for a in ["register", files / "step.mat", "--geometry", "convex", "--radius", R_MM,
                                "--angle-pitch", PITCH_DEG, "--spacing", pair.spacing[0], "auto", "--origin", 3, 0,
                                "-o", out, "--no-progress"]])
    assert rc == 0
    return out


def test_measure_outside_the_fan_names_its_span(registered, capsys):
    """A centre inside the fan's bounding box but in a corner outside the fan: the message said only the box,
    which holds the point."""
    rc, out, err = _cli(["measure", registered, "--inclusion", 4, -10, 1], capsys)
    assert rc == 2 and "not a rectangle" in err and "at y = -10 mm it spans x" in err, err
    rc, out, err = _cli(["measure", registered, "--inclusion", 9, 0, 2], capsys)
    assert rc == 0, err


def _scan_convert(p, dy=0.1):
    """The pair's RF on a Cartesian grid (range step axially, ``dy`` mm laterally), zero outside the fan."""
    from scipy import ndimage

    dr = p.spacing[0]
    X0, Y0 = p.geometry.sample_positions(p.ref.shape, p.spacing, p.origin)
    x, y = np.arange(X0.min(), X0.max(), dr), np.arange(Y0.min(), Y0.max(), dy)
    X, Y = np.meshgrid(x, y, indexing="ij")
    idx = p.geometry.physical_to_index(np.column_stack([X.ravel(), Y.ravel()]), p.ref.shape, (dr, 0), p.origin)
    inside = ((idx[0] >= 0) & (idx[0] <= p.ref.shape[0] - 1) & (idx[1] >= 0) & (idx[1] <= p.ref.shape[1] - 1))
    out = []
    for img in (p.ref, p.mov):
        v = ndimage.map_coordinates(img, idx, order=3)
        out.append(np.round(np.where(inside, v, 0.0).reshape(X.shape) * 1000).astype(np.int16).astype(float))
    return out, (dr, dy), (float(x[0]), float(y[0])), inside.reshape(X.shape)


def test_scan_converted_rf_leaves_the_zero_wedges_out(pair, tmp_path):
    """RF scan-converted with zero wedges around the fan (as a B-mode's fill): registered over the fan, NaN
    outside it, the element quality over the fan only.  Before: the wedges were registered as image (the
    full-size 3.5 MHz loop FAILED with peak hopping), and their elements read as 24 % poorly matched."""
    import matplotlib

    matplotlib.use("Agg")
    import femreg
    from femreg.plot import SUPXLABEL_WIDTH, plot_result
    from femreg.repair import poor_fraction

    (a, b), sp, org, inside = _scan_convert(pair)
    assert 0.1 < 1 - inside.mean() < 0.5                         # the wedges are a large share of the frame
    res = femreg.register(a, b, spacing=sp, origin=org, maxiter=8)
    assert "fill of value 0" in (res.excluded or ""), res.excluded
    corner = np.array([[org[0] + 0.5, org[1] + 0.5]])            # top-left wedge
    assert np.all(np.isnan(res.strain(corner)))
    assert poor_fraction(res.quality) < 0.05, poor_fraction(res.quality)
    e = np.nanmedian(res.on_grid()["exx"])
    assert -0.0125 < e < -0.0075, e                              # 1 % compression, within 25 %
    fig = plot_result(res, tmp_path / "sc.png", dpi=40)
    text = fig._supxlabel.get_text()
    assert "\n" in text and max(len(t) for t in text.splitlines()) <= SUPXLABEL_WIDTH
    assert text.replace("\n", " ") == " ".join(textwrap.wrap(text.replace("\n", " "), SUPXLABEL_WIDTH))


def test_dead_rows_stay_with_the_echo_finder(pair):
    """Zero rows at the bottom only (a recording shorter than the frame) are not a fan: find_rf_fan leaves them to
    find_echo's dead rows."""
    from femreg.echo import find_rf_fan

    ref, mov = pair.ref.copy(), pair.mov.copy()
    ref[-60:], mov[-60:] = 0.0, 0.0
    assert find_rf_fan(ref, mov, (pair.spacing[0], 0.4), (3.0, 0.0)) is None


def test_elastogram_of_scan_converted_rf_takes_the_fan(tmp_path):
    """A scan-converted RF loop (zero wedges): the elastogram is registered over the fan, as a B-mode loop's.
    Before: every pair of the 3.5 MHz loop was rejected (FAILED, peak hopping at the wedges) and no elastogram
    came out."""
    from femreg import Convex
    from femreg.elastogram import elastogram
    from forward import fields as F
    from forward.beam import make_beam_sequence

    seq = make_beam_sequence(F.compression(0.01), Convex(radius_mm=R_MM, angle_pitch_deg=PITCH_DEG), probe="L7",
                             depth_mm=12.0, n_rays=40, snr_db=30.0, seed=2, n_frames=3, step=0.008)
    frames = []
    for k in range(1, 3):
        p = type("P", (), dict(ref=seq.frames[k - 1], mov=seq.frames[k], spacing=seq.spacing, origin=seq.origin,
                               geometry=seq.geometry))
        (a, b), sp, org, inside = _scan_convert(p)
        frames += [a, b] if k == 1 else [b]
    out = elastogram(np.stack(frames), spacing=sp, origin=org, maxiter=8)
    assert out.data_mask is not None and "fill of value 0" in (out.excluded or ""), out.excluded
    assert np.isnan(out.exx[0, 0]) and np.isfinite(out.exx[out.exx.shape[0] // 2, out.exx.shape[1] // 2])
