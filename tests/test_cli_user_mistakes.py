"""The mistakes a first user makes with the in vivo recordings, as the scanner wrote them (2000 x 128 float32 raw
frames, 0.02 mm axial, 0.2 mm lateral): each one a one-line reason and exit 2 before any work, never a traceback,
a silent wrong result or an error about a temporary file.  The in vivo tests skip when the data are absent."""
import numpy as np
import pytest

from femreg.cli import main
from femreg.orientation import SMALL_FRAME_MM, diagnose
from test_io import INVIVO

SEQ = INVIVO / "seq299"
RAW = ["--shape", "2000", "128"]
needs_invivo = pytest.mark.skipif(not (SEQ / "frame1.raw").is_file(), reason=f"in vivo data not found at {SEQ}")


def _run(argv, capsys):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _frame(k=1):
    return np.fromfile(SEQ / f"frame{k}.raw", "<f4").reshape(2000, 128)


@needs_invivo
def test_spacing_in_centimetres_is_refused_by_every_command(tmp_path, capsys):
    # 0.002 0.02 (cm read as mm) gave exit 0 and a registration of a 4 x 2.56 mm image at 46 MHz
    cm = ["--spacing", "0.002", "0.02"]
    for argv in (["register", SEQ / "frame1.raw", SEQ / "frame4.raw", *RAW, *cm, "-o", tmp_path / "x.npz"],
                 ["track", SEQ, *RAW, *cm, "-o", tmp_path / "run", "--no-progress"],
                 ["elastogram", SEQ, *RAW, *cm, "-o", tmp_path / "loop", "--no-progress"]):
        rc, out, err = _run(argv, capsys)
        assert rc == 2, (argv[0], rc, err)
        assert "units look like centimetres" in err and "--spacing 0.02 0.2" in err, err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not any(tmp_path.iterdir())                  # nothing computed, nothing written
    rc, out, err = _run(["info", SEQ / "frame1.raw", *RAW, *cm], capsys)
    assert rc == 1 and "centimetres" in out             # described, but it needs the spacing in mm


@needs_invivo
def test_frame_size_rule_judges_whole_frames_only():
    rf = _frame()
    rep = diagnose(rf, (0.002, 0.02), whole_frame=True)
    assert rep.problem == "spacing" and rep.small_frame and 40 < rep.frequency_mhz < 50
    # a crop (register's echo rectangle, a user's roi) is not judged by its size: unchanged behaviour
    assert diagnose(rf, (0.002, 0.02)).problem == ""
    # a preclinical frame of its size passes: 23 MHz, 8 x 5.12 mm
    assert 0.04 * 128 > SMALL_FRAME_MM[1]                # 5.12 mm wide
    assert diagnose(rf, (0.004, 0.04), whole_frame=True).problem == ""
    # the right spacing, and the mistakes caught before, are unchanged
    assert diagnose(rf, (0.02, 0.2), whole_frame=True).problem == ""
    assert diagnose(rf, (0.2, 0.02), whole_frame=True).problem == "swapped"
    assert "metres" in diagnose(rf, (2e-5, 2e-4), whole_frame=True).message


@needs_invivo
def test_missing_output_folders_are_created_and_bad_input_leaves_none(tmp_path, capsys):
    pair = tmp_path / "a" / "b" / "pair.npz"
    rc, out, err = _run(["register", SEQ / "frame1.raw", SEQ / "frame4.raw", *RAW, "--spacing", "0.02", "0.2",
                         "-o", pair], capsys)
    assert rc == 0 and pair.is_file(), err
    rc, out, err = _run(["measure", pair, "--inclusion", "11", "13", "2.5", "--json", tmp_path / "m" / "m.json"],
                        capsys)
    assert rc == 0 and (tmp_path / "m" / "m.json").is_file(), err
    rc, out, err = _run(["plot", pair, "-o", tmp_path / "p" / "q" / "pair.png"], capsys)
    assert rc == 0 and (tmp_path / "p" / "q" / "pair.png").is_file(), err


def test_unwritable_output_is_refused_before_any_work(tmp_path, capsys):
    frames = tmp_path / "frames.npy"
    np.save(frames, np.random.default_rng(0).standard_normal((3, 64, 32)).astype(np.float32))
    # bad input: the folders made for the output are removed again
    rc, out, err = _run(["register", tmp_path / "missing.npy", frames, "--spacing", "0.02", "0.2",
                         "-o", tmp_path / "new" / "sub" / "x.npz"], capsys)
    assert rc == 2 and "no such file" in err and not (tmp_path / "new").exists()
    # a file where the folder should be: refused before reading the frames, without a temporary name
    (tmp_path / "afile").write_text("")
    for argv in (["register", frames, "--pair", "0", "1", "--spacing", "0.02", "0.2",
                  "-o", tmp_path / "afile" / "x.npz"],
                 ["invert", tmp_path / "missing.npz", "-o", tmp_path / "afile" / "mu.npz"],
                 ["measure", tmp_path / "missing.npz", "--inclusion", "1", "1", "1", "--json",
                  tmp_path / "afile" / "m.json"]):
        rc, out, err = _run(argv, capsys)
        assert rc == 2 and "is not a folder" in err and ".tmp" not in err, (argv[0], err)


def test_frame_index_errors_name_the_valid_range(tmp_path, capsys):
    frames = tmp_path / "frames.npy"
    np.save(frames, np.random.default_rng(0).standard_normal((6, 64, 32)).astype(np.float32))
    one = tmp_path / "one.npy"
    np.save(one, np.random.default_rng(1).standard_normal((64, 32)).astype(np.float32))
    sp = ["--spacing", "0.02", "0.2"]
    for argv in (["register", frames, "--pair", "0", "9", *sp, "-o", tmp_path / "x.npz"],
                 ["track", frames, "--frames", "1,9", *sp, "-o", tmp_path / "run"]):
        rc, out, err = _run(argv, capsys)
        assert rc == 2 and "counted from 0: 0 to 5" in err, (argv[0], err)
    rc, out, err = _run(["track", one, *sp, "-o", tmp_path / "run1", "--no-progress"], capsys)
    assert rc == 2 and f"{one}: one frame read" in err and "folder of per-frame files" in err, err


@needs_invivo
def test_elastogram_names_every_file_it_writes(tmp_path, capsys):
    out_dir = tmp_path / "loop"
    rc, out, err = _run(["elastogram", SEQ, *RAW, "--spacing", "0.02", "0.2", "-o", out_dir, "--no-progress"],
                        capsys)
    assert rc == 0, err
    line = [s for s in out.splitlines() if s.startswith("femreg elastogram:")][-1]
    for name in ("elastogram.npz", "elastogram.png", "pairs.csv", "pairs/"):
        assert name in line and (out_dir / name.rstrip("/")).exists(), (name, line)
    cine = [p for p in out_dir.iterdir() if p.name.startswith("strain_cine.")]
    assert len(cine) == 1 and cine[0].name in line


def test_colour_bars_mark_saturated_ends():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from femreg.plot import colorbar_extend, plot_field

    f = np.linspace(-1.0, 1.0, 50 * 40).reshape(50, 40)
    for kw, want in (({}, "both"),                              # 1-99 % limits: both tails saturate
                     ({"vmin": -2.0, "vmax": 2.0}, "neither"),
                     ({"vmin": -2.0, "vmax": 0.5}, "max")):
        fig, ax = plt.subplots()
        plot_field(f, (0.1, 0.1), ax=ax, cmap="RdBu_r", label="x (mm)", **kw)
        assert colorbar_extend(ax.images[0]) == want, kw
        cb = ax.images[0].colorbar
        assert cb.extend == want
        plt.close(fig)


def _cine_result(shape=(200, 60), spacing=(0.05, 0.2), step=4):
    """A stand-in elastogram result of a linear loop: two cine frames of a strain ramp."""
    from types import SimpleNamespace

    ramp = np.linspace(0.0, 2.0, shape[0])[:, None] * np.ones(shape)
    cine = np.stack([ramp[::step], ramp[::step][::-1]]).astype(np.float32)
    return SimpleNamespace(exx=ramp, quality=np.ones(shape), spacing=np.asarray(spacing), origin=np.array([3.0, -6.0]),
                           cine=cine, cine_spacing=np.array([step * spacing[0], spacing[1]]), cine_frames=[0, 2],
                           pairs=[dict(ref=0, mov=2, strain=-0.01, usable=True)], geometry=None,
                           to_grid=lambda v, step=1: np.asarray(v, float)[::step])


def test_strain_cine_has_mm_axes_and_colour_bars():
    """Before: the cine was two bare pixel panels, a scale of three numbers and no unit, no axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from femreg.cli.elastogram_cmd import STRAIN_LABEL, cine_figure, cine_frames

    res = _cine_result()
    b = np.random.default_rng(0).uniform(-50, 0, res.exx.shape)
    fig, (ab, ae) = cine_figure(res, b, res.spacing, res.cine[0], (0.0, 2.0), "frame 0")
    for ax in (ab, ae):
        assert ax.get_xlabel() == "lateral y (mm)" and ax.get_ylabel() == "axial x (mm)"
        # both panels on the same mm extent: depth 3 to 13 mm, lateral -6 to 6 mm (within a pixel)
        lo, hi = sorted(ax.get_ylim())
        assert abs(lo - 3.0) < 0.25 and abs(hi - 13.0) < 0.25 and abs(min(ax.get_xlim()) + 6.0) < 0.25
    assert ab.images[-1].colorbar.ax.get_ylabel() == "echo level (dB)"
    cb = ae.images[-1].colorbar
    assert cb.ax.get_ylabel() == STRAIN_LABEL and ae.images[-1].get_cmap().name == "viridis"
    assert ae.images[-1].get_clim() == (0.0, 2.0)
    plt.close(fig)
    pics = cine_frames(res, np.random.default_rng(1).normal(size=(3,) + res.exx.shape), res.spacing, (0.0, 2.0))
    assert len(pics) == 2 and pics[0].shape == pics[1].shape and pics[0].shape[0] % 16 == 0
    assert not np.array_equal(pics[0], pics[1])         # each frame its own strain image


def test_strain_cine_bmode_panel_has_no_strip_beside_the_frame():
    """An in vivo frame's size (2000 x 128 at 0.02 x 0.2 mm), cut above a noise floor: the B-mode is resampled to
    display pixels (459 x 294).  Before, that image sat half a display pixel off the frame's edge, the outline of
    the registered rectangle (on the frame's edge) stuck out past it, and autoscale's 5 % margin left a black strip
    1.28 mm wide down the B-mode panel's left edge (measured limit -7.38 mm for a frame edge at -6.1 mm)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from femreg.cli.elastogram_cmd import _cine_bmode, cine_figure
    from femreg.plot import extent_mm

    res = _cine_result(shape=(2000, 128), spacing=(0.02, 0.2))
    outside = np.zeros(res.exx.shape, bool)
    outside[1923:] = True                              # below the echo: left out of the mesh
    dx, dy = res.spacing
    roi = (3.0 - 0.5 * dx, 3.0 + 1922.5 * dx, -6.0 - 0.5 * dy, -6.0 + 127.5 * dy)     # as on_frames draws it
    frame = np.random.default_rng(2).normal(size=res.exx.shape)
    b, bsp = _cine_bmode(res, frame, res.spacing)
    assert b.shape == (459, 294)                       # resampled: the case the offset appeared in
    fig, axs = cine_figure(res, b, bsp, res.cine[0], (0.0, 2.0), outside=outside, roi=roi)
    want = extent_mm(res.exx.shape, res.spacing, res.origin)           # -6.1 ... 19.5 mm, 2.99 ... 42.99 mm
    for ax in axs:
        # rounding only (1e-9 mm); before, the B-mode panel's left limit was 1.28 mm beyond the frame's edge
        assert np.allclose([*ax.get_xlim(), *ax.get_ylim()], want, rtol=0, atol=1e-9), (ax.get_xlim(), want)
    # the B-mode image itself covers the frame's pixels (before: 0.056 mm short on the left, 0.034 mm at the top)
    assert np.allclose(axs[0].images[-1].get_extent(), want, rtol=0, atol=1e-9), axs[0].images[-1].get_extent()
    plt.close(fig)


def test_frames_given_where_a_result_belongs(tmp_path, capsys):
    # `femreg plot frames.npy` (frames, not a result) ended in a TypeError traceback and exit 1
    frames = tmp_path / "frames.npy"
    np.save(frames, np.random.default_rng(0).standard_normal((2, 64, 32)).astype(np.float32))
    for argv in (["plot", frames, "-o", tmp_path / "p.png"], ["invert", frames, "-o", tmp_path / "mu.npz"],
                 ["measure", frames, "--inclusion", "1", "1", "1"]):
        rc, out, err = _run(argv, capsys)
        assert rc == 2 and "not a result file" in err and "Traceback" not in err, (argv[0], rc, err)


def test_a_result_file_given_where_frames_belong(tmp_path, capsys):
    # register / track / info said "no 'rf' or 'frames' array; keys: ... (choose one with --variable)", pointing
    # at the result's fields; batch started its workers and ended with exit 1 and a failed task
    res, mu, el = tmp_path / "pair.npz", tmp_path / "mu.npz", tmp_path / "elastogram.npz"
    mesh = dict(mesh_points=np.zeros((4, 2)), mesh_cells=np.arange(4)[None], exx=np.zeros((8, 4)))
    np.savez(res, **mesh)
    np.savez(mu, mu=np.ones(1), **mesh)
    np.savez(el, exx=np.zeros((8, 4)), ref_frame=1, quality=np.zeros((8, 4)))
    sp = ["--spacing", "0.02", "0.2"]
    for argv, says in ((["register", res, res, *sp, "-o", tmp_path / "x.npz"], "registration result"),
                       (["track", mu, *sp, "-o", tmp_path / "run", "--no-progress"], "inversion result"),
                       (["info", res], "registration result"),
                       (["elastogram", el, *sp, "-o", tmp_path / "loop", "--no-progress"], "elastogram"),
                       (["batch", res, *sp, "-o", tmp_path / "batch", "--workers", "0", "--no-progress"],
                        "registration result")):
        rc, out, err = _run(argv, capsys)
        assert rc == 2, (argv[0], rc, err)
        assert says in err and "not RF frames" in err and "--variable" not in err, (argv[0], err)
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "batch").exists()


def test_batch_refuses_an_unreadable_recording_before_any_work(tmp_path, capsys):
    # a folder of recordings (sub-folders) passed with --folders recording: exit 1 and a failed task before
    data = tmp_path / "DATA"
    for name in ("a", "b"):
        (data / name).mkdir(parents=True)
        np.save(data / name / "f0.npy", np.zeros((64, 32), np.float32))
    rc, out, err = _run(["batch", data, "--folders", "recording", "--spacing", "0.02", "0.2", "-o",
                         tmp_path / "out", "--workers", "0", "--no-progress"], capsys)
    assert rc == 2 and "no frame files" in err and "it holds folders (a, b)" in err, (rc, err)
    assert not (tmp_path / "out").exists()


def test_frames_of_different_shapes_name_both_files(tmp_path, capsys):
    # "image shape mismatch: reference (64, 32) vs moving (48, 32)": no file named, no hint what to check
    rng = np.random.default_rng(0)
    np.save(tmp_path / "a.npy", rng.standard_normal((64, 32)).astype(np.float32))
    np.save(tmp_path / "b.npy", rng.standard_normal((48, 32)).astype(np.float32))
    rc, out, err = _run(["register", tmp_path / "a.npy", tmp_path / "b.npy", "--spacing", "0.02", "0.2",
                         "--no-orientation-check", "-o", tmp_path / "x.npz"], capsys)
    assert rc == 2 and "a.npy and" in err and "b.npy hold frames of different shapes" in err, err
    assert "64 x 32 and 48 x 32 (axial x lateral)" in err and "--shape" in err and err.count("\n") == 1, err
    assert not (tmp_path / "x.npz").exists()


def test_batch_refuses_a_setting_every_recording_lacks(tmp_path, capsys):
    # a folder of recordings without --spacing: every task failed after the workers started (exit 1, 4.2 s on the
    # in vivo folders); femreg's own results beside the recordings were counted as recordings ("its 8 files")
    from femreg.batch import jobs_from_inputs

    data = tmp_path / "DATA"
    data.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a", "b"):
        np.save(data / f"{name}.npy", rng.standard_normal((2, 64, 32)).astype(np.float32))
    np.savez(data / "pair.npz", mesh_points=np.zeros((2, 4)), mesh_cells=np.zeros((4, 1), int))
    assert [j.name for j in jobs_from_inputs([data])] == ["a", "b"]
    rc, out, err = _run(["batch", data, "-o", tmp_path / "out", "--workers", "0", "--no-progress"], capsys)
    assert rc == 2 and "spacing unknown" in err and "--spacing" in err and err.count("\n") == 1, (rc, err)
    assert not (tmp_path / "out").exists()


def test_a_given_region_without_signal_is_refused(tmp_path, capsys):
    # --depth over the in vivo frames' last 1.5 mm (zero samples): "registration failed: ... NCC after -1.000",
    # exit 1, as if the pair were bad rather than the region
    frames = np.random.default_rng(0).standard_normal((2, 200, 32)).astype(np.float32)
    frames[:, 120:] = 0.0                                  # nothing recorded below 6 mm
    np.save(tmp_path / "f.npy", frames)
    sp = ["--spacing", "0.05", "0.2", "--no-orientation-check", "--no-progress"]
    rc, out, err = _run(["register", tmp_path / "f.npy", *sp, "--depth", "6.5", "9.9", "-o", tmp_path / "x.npz"],
                        capsys)
    assert rc == 2 and "the depth given holds no signal: 69 of 69 rows" in err, (rc, err)
    rc, out, err = _run(["track", tmp_path / "f.npy", *sp, "--roi", "4", "9.9", "0", "6", "-o", tmp_path / "t"],
                        capsys)
    assert rc == 2 and "the roi given holds no signal" in err, (rc, err)
    assert not (tmp_path / "x.npz").exists() and not (tmp_path / "t").exists()


def test_elastogram_colour_range_follows_the_good_pixels():
    from femreg.elastogram import display_range

    rng = np.random.default_rng(0)
    exx = rng.lognormal(0.0, 0.8, (200, 100))               # a heavy right tail, as in vivo
    exx /= exx.mean()
    q = np.ones_like(exx)
    q[:, :20] = 0.01                                        # a decorrelated strip: low weight, wild values
    exx[:, :20] = rng.normal(0.0, 20.0, (200, 20))
    lo, hi = display_range(exx, q)
    good = exx[:, 20:]
    outside = np.mean((good < lo) | (good > hi))
    assert lo <= 1.0 <= hi and outside < 0.05, (lo, hi, outside)   # 2 + 2 % by construction
    assert hi < 10.0 and lo > -1.0, (lo, hi)                 # the strip's +-20 did not set it
    assert np.mean((good < 0) | (good > 2)) > 0.08           # the old fixed 0-2 saturated more (measured 0.10)
    assert display_range(np.full((4, 4), np.nan), np.zeros((4, 4))) == (0.0, 2.0)


@needs_invivo
def test_elastogram_in_vivo_not_saturated(tmp_path, capsys):
    # seq299 with 0-2 x the mean: 31 % of the covered pixels saturated (16 % above 2, 15 % below 0)
    base = ["elastogram", SEQ, *RAW, "--spacing", "0.02", "0.2", "--band", "0.2", "2", "--no-progress"]
    rc, out, err = _run(base + ["-o", tmp_path / "loop"], capsys)
    assert rc == 0, err
    z = np.load(tmp_path / "loop" / "elastogram.npz")
    lo, hi = z["strain_range"]
    e = z["exx"][np.isfinite(z["exx"]) & (z["quality"] > 0)]
    sat = np.mean((e < lo) | (e > hi))
    # measured 3.5 % against 22.8 % (30.9 % before the screening read the speckle's own cell and the zero rows
    # below 38.5 mm were left out)
    assert sat < 0.08 and np.mean((e < 0) | (e > 2)) > 0.15, (lo, hi, sat)
    rc, out, err = _run(["measure", tmp_path / "loop" / "elastogram.npz", "--inclusion", "12", "12", "2"], capsys)
    assert rc == 0 and "background: rest of the covered pixels" in out, out     # an elastogram has no mesh
    rc, out, err = _run(base + ["-o", tmp_path / "fixed", "--strain-range", "0", "2"], capsys)
    assert rc == 0 and list(np.load(tmp_path / "fixed" / "elastogram.npz")["strain_range"]) == [0.0, 2.0]
    rc, out, err = _run(base + ["-o", tmp_path / "bad", "--strain-range", "2", "0"], capsys)
    assert rc == 2 and "--strain-range" in err and not (tmp_path / "bad").exists(), err


def test_strain_cine_colour_bar_follows_the_range():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from femreg.cli.elastogram_cmd import cine_figure

    res = _cine_result()
    fig, (_, ae) = cine_figure(res, np.zeros(res.exx.shape) - 20, res.spacing, res.cine[0], (-0.2, 3.6))
    cb = ae.images[-1].colorbar
    assert ae.images[-1].get_clim() == (-0.2, 3.6) and 1.0 in list(cb.get_ticks())     # the mean marked
    plt.close(fig)


@needs_invivo
def test_the_same_frame_twice_is_refused(tmp_path, capsys):
    # --pair 1 1 (a typo for 1 4) ran 21 Gauss-Newton iterations on zero motion and exited 0
    sp = ["--spacing", "0.02", "0.2"]
    for argv in (["register", SEQ, *RAW, *sp, "--pair", "1", "1", "-o", tmp_path / "a.npz"],
                 ["register", SEQ / "frame2.raw", SEQ / "frame2.raw", *RAW, *sp, "-o", tmp_path / "b.npz"]):
        rc, out, err = _run(argv, capsys)
        assert rc == 2 and "identical frames" in err and len(err.strip().splitlines()) == 1, err
    assert not any(tmp_path.iterdir())


@needs_invivo
def test_frames_of_two_recordings_fail_without_numpy_noise(tmp_path, capsys):
    # seq299 frame 1 against seq304 frame 1: before, a "warning: invalid value encountered in divide" line from
    # the block matching's sub-sample fit came first
    import warnings

    with warnings.catch_warnings(record=True) as seen:     # as the command shows them, not as pytest collects
        warnings.simplefilter("always")
        rc, out, err = _run(["register", SEQ / "frame1.raw", INVIVO / "seq304" / "frame1.raw", *RAW, "--spacing",
                             "0.02", "0.2", "-o", tmp_path / "m.npz"], capsys)
    assert not [str(w.message) for w in seen if issubclass(w.category, RuntimeWarning)]
    assert rc == 1 and "warning" not in err and err.startswith("femreg register: failed: "), err
    assert "do not match" in err and (tmp_path / "m.npz").is_file()


@needs_invivo
def test_elastogram_quality_panel_not_saturated(tmp_path, capsys):
    # the weight / its median on a linear 0-3 scale saturated 22.5 % of seq299's covered pixels
    import types

    import matplotlib.pyplot as plt

    from femreg.cli.elastogram_cmd import elastogram_figure

    rc, out, err = _run(["elastogram", SEQ, *RAW, "--spacing", "0.02", "0.2", "--band", "0.2", "2", "--no-progress",
                         "-o", tmp_path / "loop"], capsys)
    assert rc == 0, err
    z = np.load(tmp_path / "loop" / "elastogram.npz")
    res = types.SimpleNamespace(exx=z["exx"], quality=z["quality"], ref_frame=int(z["ref_frame"]), n_usable=2)
    fig = elastogram_figure(res, np.ones_like(z["exx"]), z["spacing"], z["origin"])
    im = fig.axes[2].images[-1]
    q = z["quality"][z["quality"] > 0]
    lq = np.log10(q / np.median(q))
    outside = np.mean((lq < im.norm.vmin) | (lq > im.norm.vmax))
    plt.close(fig)
    assert outside < 0.05 and im.norm.vmax - im.norm.vmin > 1.0, (outside, im.norm.vmin, im.norm.vmax)


@needs_invivo
def test_no_usable_pair_is_marked_on_the_picture(tmp_path, capsys, monkeypatch):
    # seq304 with the default band (0.5-2 %; it compresses 0.35-0.56 %): exit 1, and elastogram.png, whose strain panels
    # are empty, carries the reason as a failed result's red banner (before: blank panels, nothing said)
    import femreg.plot

    banners = []
    real = femreg.plot.draw_failure
    monkeypatch.setattr(femreg.plot, "draw_failure", lambda fig, text, **kw: (banners.append(text),
                                                                               real(fig, text, **kw)))
    rc, out, err = _run(["elastogram", INVIVO / "seq304", *RAW, "--spacing", "0.02", "0.2", "--no-progress", "-o",
                         tmp_path / "loop"], capsys)
    assert rc == 1 and err.startswith("femreg elastogram: failed: no pair was usable"), err
    assert len(banners) == 1 and banners[0].startswith("NO ELASTOGRAM: no pair was usable"), banners
    # the screening reads 0.35 % over frames 0 -> 5 (0.38 % on the whole envelope's speckle cell; the registered
    # steps' affine fits sum to 0.56 %): 0.8 x that, in 0.05 % steps
    assert "--band 0.25 2" in banners[0] and (tmp_path / "loop" / "elastogram.png").is_file()


def test_raw_only_flags_on_a_file_with_a_header_are_noted(tmp_path, capsys):
    # --shape / --dtype given for an .npy (which states its own) were ignored without a word
    rng = np.random.default_rng(1)
    np.save(tmp_path / "f.npy", rng.standard_normal((2, 64, 32)).astype(np.float32))
    base = ["info", tmp_path / "f.npy", "--spacing", "0.05", "0.2"]
    rc, out, err = _run(base + ["--shape", "32", "64", "--dtype", "int16"], capsys)
    assert "--shape 32 64 (the file's frames: 2 x 64 x 32); --dtype int16 (stored as float32) ignored" in err, err
    assert "shape     64 axial x 32 lateral" in out, out                    # read as stored
    rc, out, err = _run(base + ["--shape", "64", "32", "--dtype", "float32"], capsys)
    assert "note" not in err, err                                            # what the file holds: nothing to say


@needs_invivo
def test_pair_of_a_folder_names_its_files(tmp_path, capsys):
    # --pair 1 4 meant as frame1.raw -> frame4.raw registers frame2.raw -> frame5.raw: the files are named
    rc, out, err = _run(["register", SEQ, *RAW, "--spacing", "0.02", "0.2", "--pair", "1", "4", "-o",
                         tmp_path / "p.npz", "--maxiter", "2", "--refine", "none"], capsys)
    assert rc in (0, 1) and "registering frame2.raw -> frame5.raw (frames 1 -> 4" in err, err


@pytest.mark.parametrize("command", ["register", "track", "info"])
def test_one_spacing_value_says_which_two_are_wanted(tmp_path, capsys, command):
    # argparse alone said "expected 2 arguments"; a convex / sector user needs the 'auto' form too
    path = tmp_path / "f.npy"
    np.save(path, np.zeros((3, 64, 16), np.float32))
    with pytest.raises(SystemExit) as exc:
        main([command, str(path), "--spacing", "0.02"])
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert "expected 2 arguments" in err and "--spacing DX DY" in err and "--spacing DR auto" in err, err
    with pytest.raises(SystemExit) as exc:
        main([command, str(path), "--spacing", "0.02", "0.1", "--origin", "5"])
    assert exc.value.code == 2 and "--origin X0 Y0" in capsys.readouterr().err
