"""On the command line, messages that say what to pass name the command's flags only (``--spacing 0.02 0.2``,
``--no-orientation-check``, ``--resume``, ``--shape NAX NLAT``), not the library's arguments beside them
(``check_orientation=False (CLI: ...)``, ``resume=True (--resume)``); from Python the same messages keep naming
the arguments (femreg.errors.pass_as).  A small simulated L7 pair (forward.pairs)."""
import numpy as np
import pytest

from femreg.cli import main
from femreg.errors import InputError, cli_wording, pass_as
from femreg.io import save_frames
from femreg.orientation import check

#: what only a Python caller can pass: never in a message of the command
PYTHON_WORDS = ("CLI:", "check_orientation", "resume=True", "shape=(", "frames=slice", "spacing (dx, dy)", "dtype=",
                "max_span", "max_lateral_mm", "alpha=", "femreg.register(", "model=", "maxiter=", "element_size",
                "angle_pitch_deg", "radius_mm")


def _run(argv, capsys):
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:               # argparse's refusal of a flag's value
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """``pair.npz`` (two frames, 1 % compression), its frames as ``.raw`` files and the spacing."""
    from forward import fields as F
    from forward.pairs import make_pair

    d = tmp_path_factory.mktemp("flags")
    p = make_pair(F.compression(0.01), "L7", (12.0, 8.0), 30, seed=0)
    save_frames(d / "pair.npz", np.stack([p.ref, p.mov]), tuple(p.spacing))
    np.save(d / "frames.npy", np.stack([p.ref, p.mov]))
    save_frames(d / "loop.npz", np.stack([p.ref, p.mov, p.ref]), tuple(p.spacing))
    for k, f in enumerate((p.ref, p.mov)):
        np.asarray(f, "<f4").tofile(d / f"f{k}.raw")
    return d, tuple(float(s) for s in p.spacing), p.ref.shape


def _python_free(err):
    assert not [w for w in PYTHON_WORDS if w in err], err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err


def test_pass_as_words_by_caller():
    assert pass_as("resume=True (--resume)", "--resume") == "resume=True (--resume)"
    with cli_wording():
        assert pass_as("resume=True (--resume)", "--resume") == "--resume"
        with cli_wording():
            pass
        assert pass_as("a", "b") == "b"             # nested: still the command's wording
    assert pass_as("a", "b") == "a"


def test_swapped_spacing_names_flags_only(pair, tmp_path, capsys):
    d, sp, _ = pair
    with pytest.raises(InputError) as e:             # the library keeps its arguments, with the flag beside them
        check(np.load(d / "frames.npy")[0], sp[::-1])
    assert "check_orientation=False (CLI: --no-orientation-check)" in str(e.value)
    assert f"CLI: --spacing {sp[0]:g} {sp[1]:g}" in str(e.value)
    rc, out, err = _run(["register", d / "pair.npz", "--spacing", sp[1], sp[0], "-o", tmp_path / "x.npz"], capsys)
    assert rc == 2 and "swapped" in err, err
    assert f"pass --spacing {sp[0]:g} {sp[1]:g} (axial, lateral" in err and "or --no-orientation-check" in err, err
    _python_free(err)
    assert not (tmp_path / "x.npz").exists()


def test_raw_mistakes_name_flags_only(pair, capsys):
    d, sp, shape = pair
    rc, out, err = _run(["info", d / "f0.raw"], capsys)
    assert rc == 2 and "needs --shape NAX NLAT" in err and f"--shape {shape[0]} {shape[1]}" in err, err
    _python_free(err)
    rc, out, err = _run(["info", d / "f0.raw", "--shape", *shape, "--dtype", "float64"], capsys)
    assert rc == 2 and "try --dtype float32" in err, err
    _python_free(err)
    # AXIAL LATERAL FRAMES for FRAMES AXIAL LATERAL: "frame shape (n, 1) is degenerate"
    rc, out, err = _run(["info", d / "f0.raw", "--shape", *shape, 1], capsys)
    assert rc == 2 and f"three numbers --shape is FRAMES AXIAL LATERAL, e.g. --shape 1 {shape[0]} {shape[1]}" in err
    _python_free(err)


def test_resume_and_repeated_start_name_flags_only(pair, tmp_path, capsys):
    d, sp, _ = pair
    f0, f1 = np.load(d / "frames.npy")
    loop = d / "repeat.npz"                 # frame 1 repeats frame 0: track must start at frame 1
    save_frames(loop, np.stack([f0, f0, f1]), sp)
    rc, out, err = _run(["track", loop, "-o", tmp_path / "run", "--no-progress"], capsys)
    assert rc == 2 and "start at frame 1 (--frames 1:)" in err, err
    _python_free(err)
    run = tmp_path / "run2"
    assert _run(["track", d / "pair.npz", "-o", run, "--no-progress"], capsys)[0] == 0
    rc, out, err = _run(["track", d / "pair.npz", "-o", run, "--no-progress"], capsys)
    assert rc == 2 and "use --resume or another folder" in err, err
    _python_free(err)


def test_mistyped_flag_values_are_refused_in_flag_words(pair, tmp_path, capsys):
    d, sp, _ = pair
    out = tmp_path / "x"
    cases = [
        # a threshold above 1: every pair flagged (exit 1) after the whole registration
        (["register", d / "pair.npz", "--min-ncc", "2", "-o", f"{out}.npz"], "--min-ncc: an NCC lies in -1 to 1, got '2'"),
        (["track", d / "pair.npz", "--min-ncc", "1.5", "-o", out], "--min-ncc: an NCC lies in -1 to 1"),
        # exit 0: --maxiter 0 returned the initial guess as "success", --sound-speed 0 passed unnoticed
        (["register", d / "pair.npz", "--maxiter", "0", "-o", f"{out}.npz"], "--maxiter must be an integer >= 1"),
        (["register", d / "pair.npz", "--sound-speed", "0", "-o", f"{out}.npz"], "--sound-speed must be a finite"),
        # "depth must be (d0, d1) mm with x0 < x1, got (5.0, 2.0)"
        (["register", d / "pair.npz", "--depth", "5", "2", "-o", f"{out}.npz"], "--depth D0 D1 needs D0 < D1 (mm), got 5 2"),
        (["register", d / "pair.npz", "--roi", "1", "5", "4", "2", "-o", f"{out}.npz"],
         "--roi X0 X1 Y0 Y1 needs X0 < X1 and Y0 < Y1 (mm), got 1 5 4 2"),
        # "roi (0.0, 50.0, 0.0, 4.0) mm leaves the image"
        (["register", d / "pair.npz", "--roi", "0", "50", "0", "4", "-o", f"{out}.npz"],
         "--roi 0 50 0 4 (mm) leaves the image; the image extent is x (axial)"),
        # elastogram's settings were named as its Python arguments (max_span, max_lateral_mm, workers, alpha='auto')
        (["elastogram", d / "loop.npz", "--max-span", "0", "-o", out], "--max-span must be an integer >= 1, got 0"),
        (["elastogram", d / "loop.npz", "--max-lateral", "0", "-o", out], "--max-lateral must be > 0 mm"),
        (["elastogram", d / "loop.npz", "--workers", "0", "-o", out], "--workers must be an integer >= 1, got 0"),
        (["elastogram", d / "loop.npz", "--persistence", "1", "-o", out], "--persistence must be at least 0 and below"),
        (["elastogram", d / "loop.npz", "--alpha", "auto", "-o", out], "femreg register LOOP --pair I J --alpha auto"),
        # a probe's parameters without --geometry were ignored (exit 0, registered as a linear array)
        (["track", d / "pair.npz", "--radius", "50", "-o", out], "--radius describes a convex, sector or swept probe"),
        (["register", d / "pair.npz", "--angle-pitch", "0.5", "-o", f"{out}.npz"], "pass --geometry convex, sector"),
        # "sector angle_pitch_deg must be a number in (0, 10) degrees"
        (["track", d / "pair.npz", "--geometry", "sector", "--angle-pitch", "0", "-o", out],
         "--geometry sector needs --angle-pitch above 0 and below 10 degrees"),
        # "output must be a .npz file": the flag is -o
        (["register", d / "pair.npz", "-o", f"{out}.png"], "-o must name a .npz file"),
        (["invert", d / "pair.npz", "-o", f"{out}.png"], "-o must name a .npz file"),
        # "frames must be an int, a slice or a list of ints, got slice(0, 2, 0)"
        (["track", d / "pair.npz", "--frames", "0:2:0", "-o", out], "bad frame selection '0:2:0'"),
        # "frame selection slice(2, None, None) selects no frame (the file has 2)"
        (["track", d / "pair.npz", "--frames", "2:", "-o", out],
         "frame selection 2: selects no frame (the file has 2, counted from 0: 0 to 1)"),
    ]
    res = tmp_path.parent / "flags_r.npz"          # invert's flags were named as femreg.invert's arguments
    if not res.exists():
        assert _run(["register", d / "pair.npz", "-o", res, "--no-progress"], capsys)[0] == 0
    inv = ["invert", res, "-o", f"{out}.npz"]
    cases += [([*inv, "--beta", "-1"], "--beta must be a finite number >= 0, got -1"),
              ([*inv, "--poisson", "0.3"], "--poisson applies to --model plane-strain only"),
              ([*inv, "--maxiter", "0"], "--maxiter must be an integer >= 1, got 0"),
              ([*inv, "--element-size", "0"], "--element-size must be > 0 mm, got 0"),
              ([*inv, "--region", "30", "10", "0", "2"], "--region X0 X1 Y0 Y1 needs X0 < X1 and Y0 < Y1 (mm)")]
    for argv, says in cases:
        rc, o, err = _run([*argv, "--no-progress"], capsys)
        assert rc == 2 and says in err and "slice(" not in err, (argv, rc, err)
        _python_free(err.strip().splitlines()[-1])        # argparse puts its usage lines first
    assert not any(tmp_path.iterdir())


def test_batch_folder_of_single_frames_names_the_flag_only(pair, tmp_path, capsys):
    d, sp, _ = pair
    rec = tmp_path / "rec"
    rec.mkdir()
    for k, f in enumerate(np.load(d / "frames.npy")):
        np.save(rec / f"frame{k}.npy", f)
    rc, out, err = _run(["batch", rec, "-o", tmp_path / "out", "--spacing", *sp, "--no-progress"], capsys)
    assert rc == 2 and "pass --folders recording" in err and "folders=" not in err, err
    _python_free(err)


def test_frame_flags_without_their_file_are_refused(pair, tmp_path, capsys):
    # --frame 3 without --reference was ignored: exit 0 and a picture of something else than asked
    d, sp, _ = pair
    res = tmp_path / "r.npz"
    assert _run(["register", d / "pair.npz", "-o", res, "--no-progress"], capsys)[0] == 0
    rc, out, err = _run(["plot", res, "--frame", "3", "-o", tmp_path / "p.png"], capsys)
    assert rc == 2 and "--frame 3 picks a frame of --reference FILE, and none was given" in err, err
    assert not (tmp_path / "p.png").exists()
    # likewise invert's --pair without --images (the one-step inversion it asks for was not run)
    rc, out, err = _run(["invert", res, "--pair", "0", "1", "-o", tmp_path / "m.npz", "--no-progress"], capsys)
    assert rc == 2 and "--pair 0 1 picks the frames of --images FILE(S), and none were given" in err, err
    assert not (tmp_path / "m.npz").exists()
    rc, out, err = _run(["plot", res, "--reference", d / "pair.npz", "--frame", "1", "-o", tmp_path / "p.png"],
                        capsys)
    assert rc == 0 and (tmp_path / "p.png").is_file(), err


def test_resume_with_another_spacing_names_the_setting_first(pair, tmp_path, capsys):
    # before: "spacing: ...; n_nodes: 1014 recorded, 1053 now; mesh_checksum: ...; roi: ...; pass the recorded
    # ones" (in vivo seq299, --spacing 0.02 0.21): settings nobody can pass, listed as if they could be
    d, sp, _ = pair
    run = tmp_path / "run"
    assert _run(["track", d / "pair.npz", "-o", run, "--no-progress"], capsys)[0] == 0
    rc, out, err = _run(["track", d / "pair.npz", "-o", run, "--resume", "--spacing", sp[0], 1.05 * sp[1],
                         "--no-progress"], capsys)
    assert rc == 2 and "parameters differ (spacing: " in err and "(and with it n_nodes" in err, err
    assert "n_nodes: " not in err and "mesh_checksum: " not in err, err


def test_flagged_inversion_advises_the_flag(pair, tmp_path, capsys):
    # plane stress on a plane-strain compression: flagged (exit 1), advising "try model='auto'" before
    d, sp, _ = pair
    res = tmp_path / "r.npz"
    assert _run(["register", d / "pair.npz", "-o", res, "--no-progress"], capsys)[0] == 0
    rc, out, err = _run(["invert", res, "-o", tmp_path / "mu.npz", "--model", "plane-stress", "--no-progress"],
                        capsys)
    assert rc == 1 and "contradicts the plane-stress model" in err and "try --model auto" in err, err
    assert "model='auto'" not in out + err, (out, err)


def test_a_frame_selection_names_the_files_frames(pair, tmp_path, capsys):
    # --frames 1,2: "frame 1" and frame_001.npz are the file's frame 2, which the lines did not say
    d, sp, _ = pair
    rc, out, err = _run(["track", d / "loop.npz", "--frames", "1,2", "-o", tmp_path / "run", "--no-progress"], capsys)
    assert rc == 0, err
    assert "frame   1 (the file's frame 2): ncc" in out, out
    assert "--frames selected the file's frames 1, 2: frame K and" in out, out
    rc, out, err = _run(["track", d / "loop.npz", "--frames", "0:2", "-o", tmp_path / "run2", "--no-progress"],
                        capsys)
    assert rc == 0 and "frame   1: ncc" in out and "the file's frame" not in out, out
    # elastogram: its frame indices and pairs.csv count the selection too
    f0, f1 = np.load(d / "frames.npy")
    save_frames(tmp_path / "loop4.npz", np.stack([f0, f1, f0, f1]), sp)
    rc, out, err = _run(["elastogram", tmp_path / "loop4.npz", "--frames", "1:4", "-o", tmp_path / "e",
                         "--no-progress"], capsys)
    assert rc in (0, 1), err
    assert "--frames selected the file's frames 1, 2, 3: the frame indices here and in pairs.csv" in out, out


def test_invert_progress_says_why_its_count_ends_below_the_total(capsys):
    # a log read "invert: 1/7 beta", "2/8 betas", then "done, 2/2 betas": the total shrank without a word
    from femreg.inversion import _SweepBar

    bar = _SweepBar(7, 10)
    for beta in (0.1, 0.3):
        bar.start(beta)
        bar.done()
        if beta == 0.1:
            bar.extend()            # the sweep goes past its grid
    bar.close()
    err = capsys.readouterr().err
    assert "2 beta value(s) solved of up to 8: the sweep stopped at its chosen beta" in err, err
