"""A convex frame's echo crop is said in the result, in the probe's terms: the sample-space stage leaves out the
rows past the echo (femreg.echo), and the BeamResult, its message, its file and the picture name them as ranges
along the rays (before, the result said nothing: `excluded` None, the hatched fan unexplained)."""
import numpy as np
import pytest



def _loop_with_zero_rows():
    """A 3-frame convex loop (R 40 mm, 0.6 deg, 40 rays, 16 mm of range) whose last quarter of samples is zero on
    every frame: (the sequence, its frames)."""
    from femreg import Convex
    from forward import fields as F
    from forward.beam import make_beam_sequence

    seq = make_beam_sequence(F.compression(0.01), Convex(radius_mm=40.0, angle_pitch_deg=0.6), probe="L7",
                             depth_mm=16.0, n_rays=40, snr_db=30.0, seed=1, n_frames=3, step=0.005)
    frames = seq.frames.copy()
    frames[:, 3 * frames.shape[1] // 4:] = 0.0
    return seq, frames

def test_beam_excluded_text():
    # the sentence is built from the crop's data (femreg.echo.Cut), not by rewriting echo's sentence
    from femreg.echo import Cut, EchoRegion, region_from_mm
    from femreg.geometry import beam_excluded

    rho = 100.0
    dead = "excluded: no signal (zero samples)"
    cuts = (Cut("depth", "below", 92.4, 100.0, dead), Cut("lines", "left", -52.4, -43.6, dead))
    region = EchoRegion((0, 10), (3, 9), (11, 10), (1.0, 1.0), (0.0, 0.0), "; ".join(c.text for c in cuts), cuts=cuts)
    assert region.excluded == f"depth below 92.4 mm {dead}; lines at -52.4--43.6 mm (left) {dead}", region.excluded
    t = beam_excluded(region, rho)
    assert t.startswith("range beyond 92.4 mm (along the rays) excluded"), t
    a0, a1 = np.rad2deg(-52.4 / rho), np.rad2deg(-43.6 / rho)
    assert f"rays at {a0:.1f} to {a1:.1f} deg (left)" in t, t
    assert beam_excluded(region, rho, rows_only=True) == f"range beyond 92.4 mm (along the rays) {dead}"
    g = region_from_mm((41, 20), (1.0, 1.0), (0.5, -9.5), depth=(0.0, 40.0))
    assert g.excluded == "outside the given depth x 0.0-40.0 mm, y -10.0-10.0 mm excluded", g.excluded
    assert beam_excluded(g, rho) == (f"outside the given depth: range 0.0-40.0 mm, rays at {np.rad2deg(-0.1):.1f} to "
                                     f"{np.rad2deg(0.1):.1f} deg excluded")


def test_convex_result_names_the_rows_left_out(tmp_path):
    import femreg
    from femreg import Convex
    from forward import fields as F
    from forward.beam import make_beam_pair

    p = make_beam_pair(F.compression(0.01), Convex(radius_mm=40.0, angle_pitch_deg=0.6), probe="L7",
                       depth_mm=16.0, n_rays=40, snr_db=30.0, seed=1)
    ref, mov = p.ref.copy(), p.mov.copy()
    n = ref.shape[0]
    ref[3 * n // 4:] = 0.0          # the recording stops: no samples past 3/4 of the range
    mov[3 * n // 4:] = 0.0
    res = femreg.register(ref, mov, spacing=p.spacing, origin=p.origin, geometry=p.geometry, maxiter=3)
    r_cut = p.origin[0] + (3 * n // 4 - 0.5) * p.spacing[0]
    assert res.excluded is not None and res.excluded.startswith(f"range beyond {r_cut:.1f} mm"), res.excluded
    assert res.excluded in res.message
    res.save(tmp_path / "r.npz")
    assert femreg.load_result(tmp_path / "r.npz").excluded == res.excluded


def test_convex_track_frames_name_the_rows_left_out(tmp_path):
    import femreg

    seq, frames = _loop_with_zero_rows()
    n = frames.shape[1]
    out = femreg.track(frames, spacing=seq.spacing[0], origin=seq.origin, geometry=seq.geometry, maxiter=3,
                       checkpoint_dir=tmp_path / "run")
    r_cut = seq.origin[0] + (3 * n // 4 - 0.5) * seq.spacing[0]
    for k, res in enumerate(out, start=1):
        assert res.excluded is not None and res.excluded.startswith(f"range beyond {r_cut:.1f} mm"), (k, res.excluded)
        assert femreg.load_result(tmp_path / "run" / f"frame_{k:03d}.npz").excluded == res.excluded


def test_convex_elastogram_leaves_out_the_rows_past_the_echo():
    # a convex loop whose recording stops at 3/4 of the range: the elastogram's pairs are registered on the rows
    # with echo, as register and track do (before: every pair on the whole frames, the zeros included, and the
    # result said nothing)
    from femreg import Convex
    from femreg.elastogram import elastogram
    from forward import fields as F
    from forward.beam import make_beam_sequence

    seq = make_beam_sequence(F.compression(0.01), Convex(radius_mm=40.0, angle_pitch_deg=0.6), probe="L7",
                             depth_mm=16.0, n_rays=40, snr_db=30.0, seed=2, n_frames=5, step=0.008)
    frames = seq.frames.copy()
    n = frames.shape[1]
    frames[:, 3 * n // 4:] = 0.0
    res = elastogram(frames, spacing=seq.spacing[0], origin=seq.origin, geometry=seq.geometry)
    r_cut = seq.origin[0] + (3 * n // 4 - 0.5) * seq.spacing[0]
    assert res.excluded is not None and res.excluded.startswith(f"range beyond {r_cut:.1f} mm"), res.excluded
    assert res.region is not None and tuple(res.region[0]) == (0, 3 * n // 4), res.region
    assert res.n_usable >= 1


def test_convex_mesh_panel_on_the_fields_axes():
    # without --reference the first panel draws the mesh: for a fan on the field panels' limits (before, zoomed on
    # the mesh: the panels did not line up and the rows left out were hatched as a rectangle)
    import femreg
    from femreg import Convex
    from femreg.plot import plot_result
    from forward import fields as F
    from forward.beam import make_beam_pair

    p = make_beam_pair(F.compression(0.01), Convex(radius_mm=40.0, angle_pitch_deg=0.6), probe="L7",
                       depth_mm=16.0, n_rays=40, snr_db=30.0, seed=1)
    ref, mov = p.ref.copy(), p.mov.copy()
    n = ref.shape[0]
    ref[3 * n // 4:] = 0.0
    mov[3 * n // 4:] = 0.0
    res = femreg.register(ref, mov, spacing=p.spacing, origin=p.origin, geometry=p.geometry, maxiter=2)
    fig = plot_result(res)
    mesh_ax, ux_ax = fig.axes[0], fig.axes[1]
    assert mesh_ax.get_xlim() == pytest.approx(ux_ax.get_xlim()) and mesh_ax.get_ylim() == pytest.approx(
        ux_ax.get_ylim()), (mesh_ax.get_xlim(), ux_ax.get_xlim(), mesh_ax.get_ylim(), ux_ax.get_ylim())


def test_convex_register_refuses_a_cartesian_roi(tmp_path, capsys):
    # --roi X0 X1 Y0 Y1 was read in the sample space's (range, arc length at the middle sample) and registered a
    # different region than asked, exit 0; the elastogram refused it already: register and track do too
    import femreg
    from femreg import Convex
    from femreg.cli import main
    from femreg.errors import InputError
    from forward import fields as F
    from forward.beam import make_beam_pair

    p = make_beam_pair(F.compression(0.01), Convex(radius_mm=40.0, angle_pitch_deg=0.6), probe="L7",
                       depth_mm=12.0, n_rays=40, snr_db=30.0, seed=1)
    with pytest.raises(InputError, match="depth="):
        femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin, geometry=p.geometry, roi=(5, 12, -3, 3))
    path = tmp_path / "pair.npz"
    np.savez(path, frames=np.stack([p.ref, p.mov]))
    flags = ["--geometry", "convex", "--radius", "40", "--angle-pitch", "0.6", "--spacing", f"{p.spacing[0]:.6g}",
             "auto", "--origin", f"{p.origin[0]:g}", "0", "--roi", "5", "12", "-3", "3"]
    for cmd, out in (("register", tmp_path / "r.npz"), ("track", tmp_path / "run")):
        rc = main([cmd, str(path), "-o", str(out), *flags])
        err = capsys.readouterr().err
        assert rc == 2 and "--depth D0 D1" in err, err
        assert not out.exists()
    # a --depth outside the frames, found by the first pair of a convex track: exit 2, and the run folder this
    # command made is gone again (before: left with a track.json)
    flags = flags[:-5] + ["--depth", "500", "600"]
    rc = main(["track", str(path), "-o", str(tmp_path / "run2"), *flags])
    err = capsys.readouterr().err
    assert rc == 2 and "leaves the image" in err, err
    assert not (tmp_path / "run2").exists()


def test_convex_track_record_names_the_rows_registered(tmp_path):
    # track.json's registered_region held the whole frames for a convex track whose first pair left rows out
    import json

    import femreg

    seq, frames = _loop_with_zero_rows()
    n = frames.shape[1]
    femreg.track(frames, spacing=seq.spacing[0], origin=seq.origin, geometry=seq.geometry, maxiter=3,
                 checkpoint_dir=tmp_path / "run")
    rec = json.loads((tmp_path / "run" / "track.json").read_text())
    reg = rec["registered_region"]
    assert reg["rows"] == [0, 3 * n // 4] and reg["cols"] == [0, 40], reg
    assert rec["frame_shape"] == [n, 40]
    # a resume keeps it (the record is written again at the start, before the first pair is read back)
    femreg.track(frames, spacing=seq.spacing[0], origin=seq.origin, geometry=seq.geometry, maxiter=3,
                 checkpoint_dir=tmp_path / "run", resume=True)
    rec = json.loads((tmp_path / "run" / "track.json").read_text())
    assert rec["registered_region"] == reg, rec["registered_region"]


def test_quality_map_shaped_as_the_fan():
    # a fan wider than deep: the quality map's figure follows the mesh (before: a fixed 5 x 6 in portrait, the
    # abdominal fan's axes filling 30 % of it; now 49 %)
    from skfem import MeshQuad1

    from femreg.plot import plot_quality

    m = MeshQuad1.init_tensor(np.linspace(0.0, 90.0, 10), np.linspace(-75.0, 75.0, 16))
    fig = plot_quality(m.p, m.t, np.full(m.t.shape[1], 0.9))
    w, h = fig.get_size_inches()
    assert h < w, (w, h)
    fig.canvas.draw()
    bb = fig.axes[0].get_window_extent()
    W, H = fig.canvas.get_width_height()
    assert bb.width * bb.height / (W * H) > 0.4


def test_convex_elastogram_picture_says_what_is_not_shown(tmp_path, monkeypatch):
    # elastogram.png of a convex loop cut to its echo: the footer says what was left out (before: nothing, the fan
    # simply ended), in a figure as tall as the fan's panels need (before: a fixed 13 x 5 in)
    import matplotlib

    matplotlib.use("Agg")
    import femreg.cli.elastogram_cmd as ec
    from femreg import Convex
    from femreg.cli import main
    from forward import fields as F
    from forward.beam import make_beam_sequence

    seq = make_beam_sequence(F.compression(0.01), Convex(radius_mm=40.0, angle_pitch_deg=0.6), probe="L7",
                             depth_mm=16.0, n_rays=40, snr_db=30.0, seed=2, n_frames=5, step=0.008)
    frames = seq.frames.copy()
    frames[:, 3 * frames.shape[1] // 4:] = 0.0
    path = tmp_path / "loop.npz"
    np.savez(path, frames=frames)
    seen = {}
    original = ec.elastogram_figure

    def spy(*a, **k):
        seen["fig"] = original(*a, **k)
        return seen["fig"]

    monkeypatch.setattr(ec, "elastogram_figure", spy)
    rc = main(["elastogram", str(path), "-o", str(tmp_path / "el"), "--geometry", "convex", "--radius", "40",
               "--angle-pitch", "0.6", "--spacing", f"{seq.spacing[0]:.6g}", "auto", "--origin",
               f"{seq.origin[0]:g}", "0", "--no-progress"])
    assert rc == 0
    fig = seen["fig"]
    label = fig._supxlabel.get_text() if fig._supxlabel is not None else ""
    assert "not shown: range beyond" in " ".join(label.split()), label
    assert fig.get_size_inches()[1] < 5.0
