"""A first use of the command line on frames as a scanner pipeline exports them to MATLAB: int16 frames stored
lines first (lines x samples x frames), the spacing left to scalar fields (fs in Hz, c in m/s, pitch in m) beside a
header struct and a time stamp.  The newcomer's mistakes: the spacing in metres (as the file stores it), the
transposition forgotten, a frame pair counted from 1, a B-mode drawn from another frame than the one registered.
Small simulated L7 frames (forward.pairs), written with scipy.io.savemat in tmp_path."""
import numpy as np
import pytest
import scipy.io as sio

from femreg.cli import main

#: fs = 40 MHz at 1540 m/s: c / (2 fs) = 0.01925 mm axially; the pitch 0.2 mm
FS_HZ, C_M_S, PITCH_M = 40e6, 1540.0, 2e-4
SPACING = ["--spacing", "0.01925", "0.2"]


def _run(argv, capsys):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    """``scan.mat``: three frames (1 % axial compression, then released) as int16 counts, lines x samples x
    frames, with fs, c, pitch, a header struct and a time stamp; ``frames``: the frames as femreg reads them
    (samples x lines)."""
    from forward import fields as F
    from forward.pairs import make_pair

    d = tmp_path_factory.mktemp("matlab")
    p1 = make_pair(F.compression(0.01), "L7", (12.0, 8.0), 30, seed=0)
    assert np.allclose(p1.spacing, (C_M_S / (2 * FS_HZ) * 1e3, PITCH_M * 1e3))
    frames = np.stack([p1.ref, p1.mov, p1.ref])
    counts = np.round(frames / np.abs(frames).max() * 8000).astype(np.int16)
    sio.savemat(d / "scan.mat", {"RFdata": counts.transpose(2, 1, 0), "fs": FS_HZ, "c": C_M_S, "pitch": PITCH_M,
                                 "header": {"probe": "L7-4", "txFreq": 5e6}, "timestamp": "2026-11-30T10:19:00"})
    return d, counts.astype(np.float32)


def test_transposed_frames_with_the_spacing_in_metres_get_it_in_mm(export, tmp_path, capsys):
    d, _ = export
    # as the file stores it (metres), axial first; before: "... give the spacing in that order, --spacing 0.0002
    # 1.925e-05", the metres exchanged, which the next run refused again
    for given in (["1.925e-05", "0.0002"], ["0.0002", "1.925e-05"]):
        rc, out, err = _run(["register", d / "scan.mat", "--spacing", *given, "-o", tmp_path / "r.npz"], capsys)
        assert rc == 2 and err.count("\n") <= 2, err
        assert "--transpose" in err and "metres" in err and "--spacing 0.01925 0.2 (axial, lateral" in err, err
        assert "0.0002 1.925e-05" not in err.split("look like metres")[-1]
    assert not list(tmp_path.iterdir())
    # the advice followed: registered
    rc, out, err = _run(["register", d / "scan.mat", "--transpose", *SPACING, "--pair", "0", "1", "--no-progress",
                         "-o", tmp_path / "r.npz"], capsys)
    assert rc == 0, err


def test_batch_refuses_a_pair_counted_from_1_before_any_work(export, tmp_path, capsys):
    d, _ = export
    out = tmp_path / "results"
    # before: both tasks ran, failed with "pair 1 3 requested but it holds 3 frame(s)" and exit 1, and the folder
    # then refused the corrected command ("already holds a batch")
    rc, _, err = _run(["batch", d / "scan.mat", "-o", out, "--transpose", *SPACING, "--task", "register",
                       "--pair", "1", "3", "--workers", "0", "--no-progress"], capsys)
    assert rc == 2 and "--pair 1 3: no frame 3" in err and "counted from 0: 0 to 2" in err, err
    assert err.count("\n") == 1 and not out.exists()


def test_pair_beyond_names_the_valid_range():
    from femreg.batch.inputs import pair_beyond

    assert pair_beyond((0, 5), 6) == ""
    assert pair_beyond((1, 6), 6).endswith("no frame 6: the recording holds 6 frame(s), counted from 0: 0 to 5")
    assert "no frame -1" in pair_beyond((-1, 2), 6)


@pytest.fixture(scope="module")
def pair12(export, tmp_path_factory):
    """``femreg register scan.mat --pair 1 2``: frames 1 -> 2 (the release), not frame 0."""
    d, _ = export
    out = tmp_path_factory.mktemp("pair12") / "p12.npz"
    assert main(["register", str(d / "scan.mat"), "--transpose", *SPACING, "--pair", "1", "2", "--no-progress",
                 "-o", str(out)]) == 0
    return out


def _spy_plot_result(monkeypatch) -> dict:
    """Record what ``femreg plot`` passes to femreg.plot.plot_result.  The first call draws the figure (kept under
    ``"fig"``); later ones only record their arguments and return an empty figure: the tests below ask which frame
    the command passes, and each summary figure takes seconds to draw."""
    import matplotlib.pyplot as plt

    import femreg.plot

    drawn = {}
    plot_result = femreg.plot.plot_result

    def spy(res, out, **kw):
        drawn.update(kw)
        if "fig" in drawn:
            return plt.figure()
        drawn["fig"] = plot_result(res, out, **kw)
        return drawn["fig"]

    monkeypatch.setattr(femreg.plot, "plot_result", spy)
    return drawn


def test_plot_draws_the_reference_frame_the_result_was_registered_from(export, pair12, tmp_path, capsys,
                                                                        monkeypatch):
    d, frames = export
    with np.load(pair12) as z:
        assert z["pair"].tolist() == [1, 2]
    drawn = _spy_plot_result(monkeypatch)
    rc, out, err = _run(["plot", pair12, "--reference", d / "scan.mat", "--transpose", "-o", tmp_path / "p.png"],
                        capsys)
    # before: frame 0, silently, under a result of frames 1 -> 2
    assert rc == 0 and not err, err
    assert np.array_equal(drawn["reference"], frames[1]) and drawn["bmode_title"] == "B-mode, frame 1"
    fig = drawn["fig"]                                  # the figure the command drew
    rc, out, err = _run(["plot", pair12, "--reference", d / "scan.mat", "--transpose", "--frame", "0",
                         "-o", tmp_path / "p0.png"], capsys)
    assert rc == 0 and np.array_equal(drawn["reference"], frames[0])
    assert "registered frames 1 -> 2" in err and "not its reference frame (1" in err, err
    assert fig._suptitle.get_text().startswith("frames 1 -> 2, ")
    assert fig.axes[0].get_title() == "B-mode, frame 1"


def test_invert_images_default_to_the_registered_pair(export, pair12):
    from femreg.cli import build_parser
    from femreg.cli.invert_cmd import _images

    d, frames = export
    args = build_parser().parse_args(["invert", str(pair12), "-o", "m.npz", "--images", str(d / "scan.mat"),
                                      "--transpose"])
    ref, mov = _images(args, (0.01925, 0.2))
    # before: frames 0 and 1 of the file, under a displacement of frames 1 -> 2
    assert np.array_equal(ref, frames[1]) and np.array_equal(mov, frames[2])


# ------------------------------------------------------------------------------------ B-mode of a full-depth frame
def _speckle_rf(seed=0, n=2000, m=128):
    """A full-depth RF frame (2000 samples x 128 lines) whose speckle is finer than a screen pixel axially."""
    from scipy.ndimage import convolve1d, gaussian_filter1d

    t = np.arange(-20, 21)
    pulse = np.exp(-0.5 * (t / 4.0) ** 2) * np.cos(2 * np.pi * t / 8.5)
    return gaussian_filter1d(convolve1d(np.random.default_rng(seed).standard_normal((n, m)), pulse, axis=0),
                             4.0, axis=1)


def _panel_roughness(rf):
    """Mean |difference| of vertically neighbouring screen pixels of plot_bmode's panel over their spread."""
    import matplotlib.pyplot as plt

    from femreg.plot import plot_bmode

    fig, ax = plt.subplots(figsize=(3.6, 5.5), dpi=100)
    plot_bmode(rf, (0.02, 0.2), ax=ax, colorbar=False)
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., 0].astype(float)
    bb, h = ax.get_window_extent(), img.shape[0]
    sub = img[int(h - bb.y1) + 3:int(h - bb.y0) - 3, int(bb.x0) + 3:int(bb.x1) - 3]
    plt.close(fig)
    return float(np.mean(np.abs(np.diff(sub, axis=0))) / np.std(sub))


def test_bmode_panel_is_not_aliased():
    # 2000 rows on about 420 screen rows: the nearest sample of each (before) made salt-and-pepper noise,
    # roughness 0.837 here; anti-aliased 0.760
    assert _panel_roughness(_speckle_rf()) < 0.80


def test_bmode_panel_of_the_invivo_frame_is_not_aliased():
    from test_io import INVIVO

    path = INVIVO / "seq299" / "frame1.raw"
    if not path.is_file():
        pytest.skip(f"in vivo data not found at {path}")
    # measured 0.398 with the nearest sample, 0.305 anti-aliased
    assert _panel_roughness(np.fromfile(path, "<f4").reshape(2000, 128)) < 0.35


def test_strain_cine_bmode_averages_the_samples_of_a_pixel():
    from femreg.cli.elastogram_cmd import _display
    from femreg.plot import bmode

    b = bmode(_speckle_rf())
    near, mean = (_display(b, (0.02, 0.2), average=a) for a in (False, True))
    assert near.shape == mean.shape == (320, 205)
    # mean |row-to-row step| in dB: 5.28 picking one sample of about six per row (before), 4.31 averaged
    steps = [float(np.mean(np.abs(np.diff(d, axis=0)))) for d in (near, mean)]
    assert steps[1] < 4.8 < steps[0]
    assert abs(float(np.mean(mean)) - float(np.mean(b))) < 0.1          # the level kept


# ------------------------------------------------------------------------------------------------- femreg info
def test_info_of_a_lines_first_export(export, capsys):
    d, _ = export
    rc, out, err = _run(["info", d / "scan.mat"], capsys)
    assert rc == 1, err
    # before: "shape  40 axial x 623 lateral" above a needs line saying the frames are lines x samples
    assert "shape     40 x 623 as stored: lines x samples, 623 axial x 40 lateral with --transpose" in out
    assert "axial x 623 lateral" not in out
    assert "its fields suggest --spacing 0.01925 0.2" in out and "--transpose" in out
    # the header struct's numbers are listed with the other fields
    assert "header/txFreq" in out
    rc, out, err = _run(["info", d / "scan.mat", "--transpose", *SPACING], capsys)
    assert rc == 0 and "shape     623 axial x 40 lateral" in out and "ready to register" in out, out


def test_settings_inside_a_header_struct_suggest_the_spacing(export, tmp_path, capsys):
    _, frames = export
    path = tmp_path / "p.mat"
    # the settings only in structs, one of them nested (an export's P.fs, P.Trans.pitch_mm)
    sio.savemat(path, {"rf": frames.astype(np.int16).transpose(2, 1, 0),
                       "P": {"fs": FS_HZ, "c": C_M_S, "Trans": {"pitch_mm": 0.2, "name": "L7-4"}, "id": "x"},
                       "when": "2026-11-30"})
    rc, out, err = _run(["info", path], capsys)
    # before: "no spacing found: pass --spacing DX DY", the struct's fields unseen
    assert rc == 1 and "P/fs" in out and "P/Trans/pitch_mm" in out, out
    assert "its fields suggest --spacing 0.01925 0.2" in out, out
    rc, out, err = _run(["register", path, "-o", tmp_path / "r.npz"], capsys)
    assert rc == 2 and "--spacing 0.01925 0.2" in err, err


def test_struct_fields_of_a_corrupt_struct_are_left_out(tmp_path):
    from femreg.io.mat5 import read_mat5

    path = tmp_path / "s.mat"
    sio.savemat(path, {"a": np.arange(6.0).reshape(2, 3), "h": {"fs": 1.0, "g": {"pitch": 2.0}}},
                do_compression=False)
    order, variables = read_mat5(path, path.read_bytes())
    h = {v.name: v for v in variables}["h"]
    assert {m.name: float(m.array(order).ravel()[0]) for m in h.members} == {"fs": 1.0, "g/pitch": 2.0}
    blob = bytearray(path.read_bytes())
    i = blob.find(b"pitch")
    blob[i - 8:i - 4] = (7).to_bytes(4, "little")      # the field-name element's type broken
    order, variables = read_mat5(path, bytes(blob))     # the struct's numbers dropped, the file still read
    byname = {v.name: v for v in variables}
    assert np.array_equal(byname["a"].array(order), np.arange(6.0).reshape(2, 3))
    assert [m.name for m in byname["h"].members] == ["fs"]


# ------------------------------------------------------------------------------------- numbers in other units
def test_sound_speed_and_iq_frequency_in_other_units_are_refused(export, tmp_path, capsys):
    d, _ = export
    # before: --sound-speed 1.54 passed unnoticed (exit 0); --iq-frequency in Hz upsampled every line about
    # 3e6-fold (an RF period of 0.2 nm at 4.16e6 MHz) before anything was said
    for flag, value, say in (("--sound-speed", "1.54", "km/s; pass it in m/s, --sound-speed 1540"),
                             ("--sound-speed", "1540000", "mm/s; pass it in m/s, --sound-speed 1540"),
                             ("--iq-frequency", "4160000", "Hz; pass it in MHz, --iq-frequency 4.16"),
                             ("--iq-frequency", "4160", "kHz; pass it in MHz, --iq-frequency 4.16")):
        for cmd in (["info", d / "scan.mat"], ["register", d / "scan.mat", "-o", tmp_path / "r.npz"]):
            rc, out, err = _run(cmd + ["--transpose", *SPACING, flag, value], capsys)
            assert rc == 2 and say in err and err.count("\n") == 1, (cmd, err)
    assert not list(tmp_path.iterdir())
    rc, out, err = _run(["info", d / "scan.mat", "--transpose", *SPACING, "--sound-speed", "1480"], capsys)
    assert rc == 0, err


def test_remodulate_refuses_a_frequency_in_hz():
    from femreg.errors import InputError
    from femreg.io.iq import remodulate

    iq = np.ones((16, 2), np.complex64)
    with pytest.raises(InputError, match=r"modulation_frequency=4.16 \(CLI: --iq-frequency 4.16\)"):
        remodulate(iq, 0.08, 4.16e6)
    rf, dz, up = remodulate(iq, 0.08, 4.16)
    assert up == 4 and rf.shape == (61, 2)          # 8 samples per RF period of 0.185 mm


def test_measure_names_metres_and_a_background_beyond_the_mesh(pair12, tmp_path, capsys):
    rc, out, err = _run(["measure", pair12, "--inclusion", "0.006", "0.004", "0.002"], capsys)
    # before: only "lies outside the mesh", the metres unnamed
    assert rc == 2 and "look like metres: pass them in mm, --inclusion 6 4 2" in err, err
    rc, out, err = _run(["measure", pair12, "--inclusion", "6", "4", "2", "--background", "1", "11", "-5", "20",
                         "--json", tmp_path / "m.json"], capsys)
    # before: cut to the mesh without a word, where an inclusion reaching beyond it got a note
    assert rc == 0 and "note: the background box extends beyond the mesh" in out, out
    rc, out, err = _run(["measure", pair12, "--inclusion", "6", "4", "2", "--background", "2", "10", "2", "6"],
                        capsys)
    assert rc == 0 and "note:" not in out, out


def test_invert_names_a_reference_modulus_in_pa(pair12, tmp_path, capsys):
    from femreg.cli.invert_cmd import _boxes

    args = type("A", (), {"region": None, "reference": [2.0, 10.0, 2.0, 6.0, 10000.0]})()
    region, reference = _boxes(args, False)
    err = capsys.readouterr().err
    # before: 10000 kPa taken as given, Young's moduli of 10 MPa written without a word
    assert reference[1] == 10000.0 and "if it is in Pa, pass 10" in err, err
    args.reference[-1] = 0.01
    _boxes(args, False)
    assert "if it is in MPa, pass 10" in capsys.readouterr().err
    args.reference[-1] = 25.0
    _boxes(args, False)
    assert capsys.readouterr().err == ""


def test_invert_prints_a_readable_result_line(pair12, tmp_path, capsys):
    rc, out, err = _run(["invert", pair12, "-o", tmp_path / "mu.npz", "--beta", "0.1", "--no-uncertainty",
                         "--no-progress"], capsys)
    line = out.splitlines()[0]
    # before: the library's repr, "InversionResult(model='plane-strain', beta=0.1, n_el=..., success=True, ..."
    assert rc in (0, 1) and line.startswith("inversion: ") and ", model plane-" in line, out
    assert "InversionResult(" not in out and "=" not in line.split(";")[0], out
    assert ("flagged" in line) == (rc == 1)


def test_a_file_spacing_written_axial_first_under_transpose(export, tmp_path, capsys):
    _, frames = export
    path = tmp_path / "s.mat"
    # lines-first frames with their spacing written as (axial, lateral): --transpose exchanges it with the axes
    sio.savemat(path, {"rf": frames.astype(np.int16).transpose(2, 1, 0), "spacing": [0.01925, 0.2]})
    for cmd in (["info", path, "--transpose"], ["register", path, "--transpose", "-o", tmp_path / "r.npz"]):
        rc, out, err = _run(cmd, capsys)
        text = out if cmd[0] == "info" else err
        # before: "--spacing 0.2 0.01925 (axial, lateral mm) gives ...", a flag never typed, the cause unnamed
        assert rc == (1 if cmd[0] == "info" else 2), text
        assert "the file's spacing 0.2 0.01925 (axial, lateral mm) gives" in text, text
        assert "pass --spacing 0.01925 0.2" in text and "--transpose exchanged it with the file's axes" in text
    assert not (tmp_path / "r.npz").exists()
    # typed on the command line, the same spacing is named as the flag
    rc, out, err = _run(["register", path, "--transpose", "--spacing", "0.2", "0.01925", "-o", tmp_path / "r.npz"],
                        capsys)
    assert rc == 2 and "--spacing 0.2 0.01925 (axial, lateral mm) gives" in err and "the file's" not in err, err


def test_plot_of_a_track_run_on_a_selection_draws_its_first_frame(export, tmp_path, capsys, monkeypatch):
    import json

    d, frames = export
    run = tmp_path / "run"
    rc, out, err = _run(["track", d / "scan.mat", "--transpose", *SPACING, "--frames", "1:", "-o", run,
                         "--no-progress"], capsys)
    assert rc == 0 and json.loads((run / "track.json").read_text())["file_frames"] == [1, 2], err
    drawn = _spy_plot_result(monkeypatch)
    rc, out, err = _run(["plot", run / "frame_001.npz", "--reference", d / "scan.mat", "--transpose",
                         "-o", tmp_path / "f.png"], capsys)
    # before: the file's frame 0 under a run registered on its frame 1
    assert rc == 0 and np.array_equal(drawn["reference"], frames[1]) and drawn["bmode_title"] == "B-mode, frame 1"
    # the selection given to plot too: its frame 0, as before
    rc, out, err = _run(["plot", run / "frame_001.npz", "--reference", d / "scan.mat", "--transpose",
                         "--frames", "1:", "-o", tmp_path / "g.png"], capsys)
    assert rc == 0 and np.array_equal(drawn["reference"], frames[1]) and not err, err
    # invert --images: the run's frames 0 -> 1 are the file's 1 -> 2 (before: the file's 0 and 1; on the in vivo
    # seq304, frame 5 of a track run: image term 743 with frames 0, 1 against 117 with frames 0, 5)
    from femreg.cli import build_parser
    from femreg.cli.invert_cmd import _images

    args = build_parser().parse_args(["invert", str(run / "frame_001.npz"), "-o", "m.npz", "--images",
                                      str(d / "scan.mat"), "--transpose"])
    ref, mov = _images(args, (0.01925, 0.2))
    assert np.array_equal(ref, frames[1]) and np.array_equal(mov, frames[2])


def test_elastogram_band_given_as_fractions_is_refused(export, tmp_path, capsys):
    d, _ = export
    # before: the loop was screened, then exit 1 with "raise the band, e.g. --band 0.005 0.5"
    rc, out, err = _run(["elastogram", d / "scan.mat", "--transpose", *SPACING, "--band", "0.005", "0.02",
                         "-o", tmp_path / "e", "--no-progress"], capsys)
    assert rc == 2 and "as fractions it is --band 0.5 2" in err and err.count("\n") == 1, err
    assert not (tmp_path / "e").exists()


def test_element_size_in_metres_is_refused_before_any_work(export, tmp_path, capsys):
    d, frames = export
    # before: 0.0015 mm meshed one pixel per element (623 x 40 frames: about 24000 elements; 1923 x 128 in vivo:
    # about 246000) and register, track and batch ran on without end; elastogram after its screening
    for cmd in (["register", d / "scan.mat", "--pair", "0", "1", "-o", tmp_path / "r.npz"],
                ["track", d / "scan.mat", "-o", tmp_path / "t"], ["elastogram", d / "scan.mat", "-o", tmp_path / "e"],
                ["batch", d / "scan.mat", "-o", tmp_path / "b", "--workers", "0"]):
        rc, out, err = _run(cmd + ["--transpose", *SPACING, "--element-size", "0.0015", "--no-progress"], capsys)
        assert rc == 2 and "is smaller than a pixel (0.01925 x 0.2 mm" in err, (cmd[0], err)
        assert "read as metres it is --element-size 1.5" in err and err.count("\n") == 1, err
    assert not list(tmp_path.iterdir())


def test_register_refuses_an_element_size_below_a_pixel():
    import femreg
    from femreg.errors import InputError
    from femreg.mesh import check_element_size

    ref = np.random.default_rng(0).standard_normal((64, 16))
    with pytest.raises(InputError, match=r"element_size 0.001 0.002 mm is smaller than a pixel .*"
                                         r"element_size=1 2 \(CLI: --element-size 1 2\)"):
        femreg.register(ref, ref, spacing=(0.02, 0.2), element_size=(0.001, 0.002))
    check_element_size((0.5, 0.1), (0.02, 0.2))     # below a pixel laterally only: one line per element, allowed
    check_element_size(0.001, (0.02, 0.2), mesh=object())     # a given mesh: its own elements


def test_roi_and_depth_in_metres_are_named(export, tmp_path, capsys):
    d, _ = export
    # before: "holds fewer than 2 x 2 pixels" and the image extent, the metres unnamed
    for flag, values, say in (("--roi", ["0.002", "0.01", "0.001", "0.007"], "--roi 2 10 1 7"),
                              ("--depth", ["0.002", "0.01"], "--depth 2 10")):
        rc, out, err = _run(["register", d / "scan.mat", "--transpose", *SPACING, "--pair", "0", "1", flag, *values,
                             "-o", tmp_path / "r.npz"], capsys)
        assert rc == 2 and f"the numbers look like metres: pass them in mm, {say}" in err, err
    # a region really too small gets no such hint
    rc, out, err = _run(["register", d / "scan.mat", "--transpose", *SPACING, "--pair", "0", "1", "--roi", "2", "2.01",
                         "1", "7", "-o", tmp_path / "r.npz"], capsys)
    assert rc == 2 and "fewer than 2 x 2 pixels" in err and "metres" not in err, err


def test_a_range_written_as_in_prose_gets_its_slice():
    from femreg.errors import InputError
    from femreg.options import frame_selection

    for text, say in (("1-5", "frames 1 to 5 are 1:6"), ("0..4", "frames 0 to 4 are 0:5")):
        with pytest.raises(InputError, match=say):         # before: only the forms, the slice's end unexplained
            frame_selection(text)
    with pytest.raises(InputError) as info:
        frame_selection("a-b")
    assert "are" not in str(info.value)
    assert frame_selection("1:6") == slice(1, 6)


def test_batch_task_errors_speak_in_flags_and_name_the_settings_file(export, tmp_path, capsys):
    import shutil

    d, _ = export
    src = tmp_path / "data"
    src.mkdir()
    for name in ("a.mat", "b.mat"):
        shutil.copy(d / "scan.mat", src / name)
    (src / "b.femreg.toml").write_text("spacing = [1.925e-05, 2e-04]\n")     # metres, in b's own settings
    rc, out, err = _run(["batch", src, "-o", tmp_path / "out", "--transpose", *SPACING, "--task", "register",
                         "--workers", "0", "--no-progress"], capsys)
    # before: "FAILED b/pair_000-001: OrientationError: ... pass it in mm, (0.01925, 0.2) (...; CLI: --spacing
    # 0.01925 0.2), or check_orientation=False (CLI: --no-orientation-check)", the settings file unnamed; then a
    # failed task (exit 1); now every recording is checked before any work (exit 2)
    assert rc == 2 and err.count("\n") == 1 and "b.mat: " in err and "metres" in err, err
    assert "--spacing 0.01925 0.2" in err and "check_orientation" not in err, err
    assert "b.femreg.toml beside the recording sets its own settings" in err, err
    assert not (tmp_path / "out").exists()


def test_registered_frames_of_each_kind_of_result(tmp_path):
    import json

    from femreg.cli._common import registered_frames

    np.savez(tmp_path / "p.npz", pair=np.array([3, 7]))
    np.savez(tmp_path / "frame_004.npz", frame=np.array(4), increment=np.zeros(2))
    np.savez(tmp_path / "other.npz", u=np.zeros(2))
    assert registered_frames(tmp_path / "p.npz")[:2] == (3, 7)
    assert registered_frames(tmp_path / "frame_004.npz")[:2] == (0, 4)        # accumulated: frames 0 -> 4
    assert registered_frames(tmp_path / "other.npz") is None
    (tmp_path / "track.json").write_text(json.dumps({"file_frames": [2, 4, 6, 8, 10]}))
    assert registered_frames(tmp_path / "frame_004.npz")[:2] == (2, 10)       # a run on --frames 2::2


def test_no_elastogram_draws_no_colour_bar_over_empty_panels(export, tmp_path, capsys, monkeypatch):
    import femreg.cli.elastogram_cmd as E

    d, _ = export
    figs = []
    draw = E.elastogram_figure
    monkeypatch.setattr(E, "elastogram_figure", lambda *a, **k: figs.append(draw(*a, **k)) or figs[-1])
    rc, out, err = _run(["elastogram", d / "scan.mat", "--transpose", *SPACING, "--band", "5", "10",
                         "-o", tmp_path / "e", "--no-progress"], capsys)
    assert rc == 1 and "no pair was usable" in err and len(figs) == 1, err
    # before: the empty strain and quality panels kept colour bars over 0-2 and 0.1-10, ranges of no data
    shown = [ax.images[-1].colorbar.ax.get_visible() for ax in figs[0].axes]
    assert shown == [True, False, False], shown


def test_a_spacing_against_the_files_fields_is_noted(export, capsys):
    d, _ = export
    rc, out, err = _run(["info", d / "scan.mat", "--transpose", "--spacing", "0.025", "0.2"], capsys)
    # before: "needs nothing: ready to register", every depth 30 % off without a word; 30 % from c / (2 fs) is
    # more than tissue's speed of sound explains: a need now (register refuses it, femreg.orientation.check_sampling)
    assert rc == 1 and "the axial spacing 0.025 mm given implies 30.8 MHz sampling" in out, out
    assert "--spacing differs from what the file's fields imply (axial 0.025 mm against 0.01925" in err
    assert "lateral" not in err.split("imply (")[1].split(":")[0], err
    rc, out, err = _run(["info", d / "scan.mat", "--transpose", "--spacing", "0.0205", "0.2"], capsys)
    assert rc == 0 and "implies" not in out and "(axial 0.0205 mm against 0.01925" in err   # 6.5 %: a note only
    rc, out, err = _run(["info", d / "scan.mat", "--transpose", *SPACING], capsys)
    assert rc == 0 and "note" not in err, err


# ------------------------------------------------------------------------------------------ a later newcomer pass
def test_text_variables_are_listed_with_their_text(export, tmp_path, capsys):
    d, _ = export
    rc, out, err = _run(["info", d / "scan.mat"], capsys)
    # before: "array     timestamp        1 char", the text (and its length) unseen
    assert "array     timestamp        1x19 char '2026-11-30T10:19:00'" in out, out
    # before: a note that "--spacing" (never typed: info's stand-in 1 mm) differs from the file's fields
    assert rc == 1 and "--spacing differs" not in err, err
    path = tmp_path / "t.mat"
    sio.savemat(path, {"fs": FS_HZ, "when": "2026-11-30", "note": "compression by hand, " * 5})
    rc, out, err = _run(["register", path, *SPACING, "-o", tmp_path / "r.npz"], capsys)
    # before: "(variables: fs, note, when)"
    assert rc == 2 and "(variables: fs, note = 'compression by hand, compression by h...', when = '2026-11-30')" \
        in err, err
    rc, out, err = _run(["info", path, "--variable", "rf"], capsys)
    assert rc == 2 and "available: fs, note = " in err and "when = '2026-11-30'" in err, err


def test_text_of_a_v73_char_variable_is_listed(tmp_path, capsys):
    import h5py

    from femreg.io.matlab import write_mat

    path = tmp_path / "s73.mat"
    write_mat(path, np.zeros((2, 20, 20), np.float32), version="7.3")
    with h5py.File(path, "a") as f:
        del f["rf"]
        ds = f.create_dataset("when", data=np.array([[ord(c)] for c in "2026-11-30"], np.uint16))
        ds.attrs["MATLAB_class"] = np.bytes_("char")
    rc, out, err = _run(["info", path], capsys)
    assert rc == 2 and "(variables: origin, when = '2026-11-30')" in err, err


def _inversion_with_uncertainty(unc):
    from skfem import MeshQuad1

    from femreg.inversion import InversionResult

    m = MeshQuad1.init_tensor(np.linspace(0, 20, 11), np.linspace(-8, 8, 9))
    u = np.zeros(2 * m.p.shape[1])
    u[0::2] = -0.01 * m.p[0]
    res = InversionResult(mesh=m, mu=np.ones(m.t.shape[1]), model="plane-stress", lambda_bar=2.0, beta=0.01,
                          u_measured=u, success=True, message="ok")
    res.uncertainty = unc(m.t.shape[1])
    return res


def test_uncertainty_colour_bar_spans_the_data_and_names_its_ends():
    import matplotlib.pyplot as plt

    from femreg.plot import UNCERTAINTY_MIN_SPAN, plot_inversion

    res = _inversion_with_uncertainty(lambda n: np.linspace(0.2, 0.3, n))
    fig = plot_inversion(res, dpi=40)
    ax = [a for a in fig.axes if a.get_title()][1]
    norm, label = ax.collections[0].norm, ax.child_axes[0].get_ylabel()
    # before: 0 to 0.3, the darkest third of the scale (0 = certain) on no element, the ends unnamed
    assert norm.vmin == pytest.approx(0.201, abs=1e-3) and norm.vmax == pytest.approx(0.299, abs=1e-3)
    assert "low: more certain, high: less certain" in label, label
    plt.close(fig)
    fig = plot_inversion(_inversion_with_uncertainty(lambda n: np.full(n, 0.01)), dpi=40)
    norm = [a for a in fig.axes if a.get_title()][1].collections[0].norm
    # a uniform uncertainty: the least span, never below 0 (not a pattern stretched over the scale)
    assert norm.vmin == 0.0 and norm.vmax == pytest.approx(UNCERTAINTY_MIN_SPAN)
    plt.close(fig)


def test_batch_checks_every_recording_before_any_work(export, tmp_path, capsys):
    import shutil

    d, frames = export
    src = tmp_path / "data"
    src.mkdir()
    shutil.copy(d / "scan.mat", src / "a.mat")
    # b stored samples first: under --transpose (right for a) its frames are lines x samples
    sio.savemat(src / "b.mat", {"RFdata": frames.astype(np.int16).transpose(1, 2, 0)})
    out = tmp_path / "out"
    rc, _, err = _run(["batch", src, "-o", out, "--transpose", *SPACING, "--task", "register", "--workers", "0",
                       "--no-progress"], capsys)
    # before: a registered, b's task ran and failed on its orientation (exit 1), advised to pass --transpose
    assert rc == 2 and "b.mat: " in err and "transposed" in err and "a.mat" not in err, err
    assert "leave out --transpose for this recording (b.femreg.toml beside it: transpose = false)" in err, err
    assert err.count("\n") == 1 and not out.exists(), err
    rc, _, err = _run(["register", src / "b.mat", "--transpose", *SPACING, "-o", tmp_path / "r.npz"], capsys)
    # before: "transpose them (--transpose)", the flag given
    assert rc == 2 and "leave out --transpose (the file stores them samples first" in err, err
    assert "transpose them (--transpose)" not in err
    (src / "b.femreg.toml").write_text("transpose = false\n")      # b's own settings right: both run
    rc, _, err = _run(["batch", src, "-o", out, "--transpose", *SPACING, "--task", "register", "--workers", "0",
                       "--no-progress"], capsys)
    assert rc in (0, 1) and "FAILED" not in err, err


def test_counts_take_their_number():
    import re
    from pathlib import Path

    import femreg
    from femreg.batch.summary import BatchSummary
    from femreg.errors import counted

    assert (counted(1, "node"), counted(0, "node"), counted(3, "node")) == ("1 node", "0 nodes", "3 nodes")
    s = BatchSummary(out_dir=Path("."), records=[{"key": "a/track", "status": "ok"}], wall_s=1.0, workers="0")
    assert s.to_markdown().startswith("# femreg batch: 1 task, 0 failed")      # before: "1 tasks"
    # before: "peak hopping at 1 nodes reseeded" and alike, a count of any size before a plural noun
    bare = re.compile(r"\{int\([^{}]*\)\} (nodes|elements|rows|columns)\b")
    found = [f"{p.name}:{k + 1}" for p in Path(femreg.__file__).parent.rglob("*.py")
             for k, line in enumerate(p.read_text().splitlines()) if bare.search(line)]
    assert not found, found
