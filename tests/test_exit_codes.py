"""One meaning for every exit code of every command: 0 done; 1 computed but failed or flagged (the result is
still written and the reason printed); 2 bad input, found before any work (one line on stderr).  The matrix
commands x outcomes runs on small simulated L7 pairs: a compressed pair (registers), two unrelated speckle
frames (do not match: the registration fails) and the pair transposed (refused by the orientation check)."""
import contextlib
import io
import json

import numpy as np
import pytest

from femreg.cli import main
from femreg.io import save_frames

SIZE = (12.0, 8.0)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from forward import fields as F
    from forward.pairs import make_pair

    d = tmp_path_factory.mktemp("exit")
    good = make_pair(F.compression(0.01), "L7", SIZE, 30, seed=0)
    other = make_pair(F.compression(0.01), "L7", SIZE, 30, seed=1)
    sp = tuple(good.spacing)
    save_frames(d / "good.npz", np.stack([good.ref, good.mov]), sp)
    save_frames(d / "unrelated.npz", np.stack([good.ref, other.ref]), sp)
    save_frames(d / "transposed.npz", np.stack([good.ref.T, good.mov.T]), sp[::-1])
    for k, frame in enumerate((good.ref, good.mov)):
        (d / "perframe").mkdir(exist_ok=True)
        save_frames(d / "perframe" / f"frame{k + 1}.npz", frame[None], sp)
    return d


def _run(argv, capsys):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


#: (exit code, stdout, stderr) of the two registrations behind :func:`results`, checked by test_register
RUNS = {}


@pytest.fixture(scope="module")
def results(data):
    """A successful and a failed registration result file (made once; their own exit codes are tested below)."""
    for name, out in (("good", "ok"), ("unrelated", "failed")):
        o, e = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(o), contextlib.redirect_stderr(e):
            rc = main(["register", str(data / f"{name}.npz"), "-o", str(data / f"{out}.npz")])
        RUNS[name] = rc, o.getvalue(), e.getvalue()
    return data / "ok.npz", data / "failed.npz"


def test_register(data, results, capsys, tmp_path):
    import femreg

    assert femreg.load_result(results[0]).success
    failed = femreg.load_result(results[1])
    assert not failed.success                                   # written, and says so
    assert "converged" not in failed.message, failed.message   # no "FAILED: converged: ..."
    rc, out, err = RUNS["unrelated"]                            # the fixture's runs, not registered again
    assert rc == 1 and results[1].is_file() and "registration failed" in err and "FAILED" not in err
    # a failed computation reads differently from bad input (exit 2, "error:"), so a log tells them apart
    assert err.startswith("femreg register: failed: ") and "error:" not in err, err
    reason = failed.message.removeprefix("FAILED: ")
    assert (out + err).count(reason) == 1, out + err            # said once, as the error line
    rc, out, err = RUNS["good"]
    assert rc == 0 and err == "", err
    rc, out, err = _run(["register", data / "transposed.npz", "-o", tmp_path / "t.npz"], capsys)
    assert rc == 2 and "transposed" in err and err.count("\n") == 1 and not (tmp_path / "t.npz").exists()
    rc, out, err = _run(["register", data / "transposed.npz", "-o", tmp_path / "t.npz", "--no-orientation-check",
                         "--maxiter", "1"], capsys)
    assert rc in (0, 1) and (tmp_path / "t.npz").is_file()      # the override runs it
    rc, out, err = _run(["register", data / "perframe" / "frame1.npz", "-o", tmp_path / "one.npz"], capsys)
    assert rc == 2 and "holds one frame: give the moving frame's file too" in err and err.count("\n") == 1
    # with --pair given, no advice to pass --pair: the file has no second frame to pick
    rc, out, err = _run(["register", data / "perframe" / "frame1.npz", "--pair", "0", "1", "-o",
                         tmp_path / "one.npz"], capsys)
    assert rc == 2 and "--pair 0 1 has no second frame to pick" in err and "--pair I J" not in err, err


def test_track(data, capsys, tmp_path):
    rc, out, err = _run(["track", data / "good.npz", "-o", tmp_path / "ok", "--no-progress"], capsys)
    assert rc == 0 and "FLAGGED" not in out + err, out + err
    rc, out, err = _run(["track", data / "unrelated.npz", "-o", tmp_path / "bad", "--no-progress"], capsys)
    assert rc == 1 and "FLAGGED" in err and (tmp_path / "bad" / "frame_001.npz").is_file(), out + err
    assert "FAILED: " not in out + err                          # "registration failed: <reason>", said once
    rc, out, err = _run(["track", data / "transposed.npz", "-o", tmp_path / "t", "--no-progress"], capsys)
    assert rc == 2 and "transposed" in err and not (tmp_path / "t").exists()


def test_batch(data, capsys, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    (src / "good.npz").write_bytes((data / "good.npz").read_bytes())
    base = ["batch", "--workers", "0", "--no-progress"]
    rc, out, err = _run(base + [src, "-o", tmp_path / "ok"], capsys)
    assert rc == 0, out + err
    (src / "unrelated.npz").write_bytes((data / "unrelated.npz").read_bytes())
    rc, out, err = _run(base + [src, "-o", tmp_path / "flag"], capsys)
    assert rc == 1 and "FLAGGED unrelated/track" in err, out + err
    rc, out, err = _run(base + [src, "-o", tmp_path / "pairs", "--task", "register"], capsys)
    assert rc == 1 and "FAILED unrelated/pair_000-001" in err and "FAILED: " not in err, err
    assert (tmp_path / "pairs" / "unrelated" / "pair_000-001.npz").is_file()   # the result is kept
    # one file per frame: refused before anything runs, pointing to --folders recording
    for task in ("track", "register"):
        rc, out, err = _run(base + [data / "perframe", "-o", tmp_path / f"pf-{task}", "--task", task], capsys)
        assert rc == 2 and "--folders recording" in err and not (tmp_path / f"pf-{task}").exists(), err
    rc, out, err = _run(base + [data / "perframe", "-o", tmp_path / "pf", "--folders", "recording"], capsys)
    assert rc == 0, out + err
    rc, out, err = _run(base + [data / "transposed.npz", "-o", tmp_path / "t"], capsys)
    assert rc == 2 and "transposed" in err and not (tmp_path / "t").exists()


def test_invert(results, capsys, tmp_path):
    ok, failed = results
    rc, out, err = _run(["invert", ok, "-o", tmp_path / "mu.npz", "--no-progress"], capsys)
    assert rc == 0 and (tmp_path / "mu.npz").is_file() and err == "", err
    assert "modulus contrast over the mesh" in out
    rc, out, err = _run(["invert", failed, "-o", tmp_path / "f.npz"], capsys)
    assert rc == 2 and "failed registration" in err and "--allow-failed" in err and not (tmp_path / "f.npz").exists()
    rc, out, err = _run(["invert", failed, "-o", tmp_path / "f.npz", "--allow-failed"], capsys)
    assert rc == 1 and "FLAGGED" in err and (tmp_path / "f.npz").is_file()
    rc, out, err = _run(["invert", ok, "-o", tmp_path / "r.npz", "--region", "0", "500", "-4", "4"], capsys)
    assert rc == 2 and "the mesh spans x" in err, err
    import femreg

    p = femreg.load_result(ok).mesh.p
    lo, hi = p.min(axis=1), p.max(axis=1)
    inner = np.column_stack([lo + 0.2 * (hi - lo), hi - 0.2 * (hi - lo)]).ravel()    # x0 x1 y0 y1 inside
    rc, out, err = _run(["invert", ok, "-o", tmp_path / "r.npz", "--region", *inner], capsys)
    assert rc == 0 and "modulus contrast over the region" in out, err


def test_plot(results, capsys, tmp_path):
    ok, failed = results
    rc, out, err = _run(["plot", ok, "-o", tmp_path / "ok.png", "--dpi", "30"], capsys)
    assert rc == 0 and (tmp_path / "ok.png").is_file() and err == "", err
    rc, out, err = _run(["plot", failed, "-o", tmp_path / "f.png", "--dpi", "30"], capsys)
    assert rc == 1 and (tmp_path / "f.png").is_file() and "failed" in err, err
    main(["invert", str(failed), "-o", str(tmp_path / "mu.npz"), "--allow-failed"])
    capsys.readouterr()
    rc, out, err = _run(["plot", tmp_path / "mu.npz", "-o", tmp_path / "m.png", "--dpi", "30"], capsys)
    assert rc == 1 and (tmp_path / "m.png").is_file() and "failed registration" in err, err   # drawn, said
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    rc, out, err = _run(["plot", tmp_path / "junk.npz", "-o", tmp_path / "j.png"], capsys)
    assert rc == 2 and err.count("\n") == 1


def test_info(data, capsys, tmp_path):
    rc, out, err = _run(["info", data / "good.npz"], capsys)
    assert rc == 0 and "ready to register" in out
    rc, out, err = _run(["info", data / "transposed.npz", "--json"], capsys)
    info = json.loads(out)
    assert rc == 1 and info["shape"] == [int(np.load(data / "transposed.npz")["rf"].shape[1]),
                                         int(np.load(data / "transposed.npz")["rf"].shape[2])]
    assert any("transposed" in n for n in info["needs"])
    (tmp_path / "x.raw").write_bytes(b"\0" * 64)
    rc, out, err = _run(["info", tmp_path / "x.raw"], capsys)
    assert rc == 2 and "--shape" in err and err.count("\n") == 1


def test_auto_alpha_without_a_successful_candidate_says_so(data, capsys, tmp_path):
    import femreg

    z = np.load(data / "unrelated.npz")
    with pytest.warns(RuntimeWarning, match="none of the 7 candidate"):
        res = femreg.register(z["rf"][0], z["rf"][1], spacing=tuple(z["spacing"]), alpha="auto")
    assert not res.success and res.auto_alpha.n_successful == 0
    assert "found no successful candidate" in res.message and "converged" not in res.message, res.message
    with pytest.warns(RuntimeWarning):
        rc, out, err = _run(["register", data / "unrelated.npz", "-o", tmp_path / "a.npz", "--alpha", "auto"], capsys)
    assert rc == 1 and "no successful candidate" in err


def test_every_command_states_its_exit_codes_in_its_help():
    # register, elastogram, batch and invert said nothing about them; info, plot, measure and track each in their
    # own words.  Now every one ends with "exit codes: 0 ...; 1 ...; 2 bad input, found before any work ..."
    from femreg.cli import EXIT_CODES, build_parser

    sub = next(a for a in build_parser()._actions if getattr(a, "choices", None) and "register" in a.choices)
    assert set(EXIT_CODES) == {"register", "track", "elastogram", "info", "plot", "measure", "batch", "invert"}
    for name in EXIT_CODES:
        text = " ".join(sub.choices[name].format_help().split())
        assert "exit codes: 0 " in text and "; 1 " in text and "; 2 bad input, found before any work" in text, name
    for name in ("track", "batch"):                              # --mode said what its two choices do
        text = " ".join(sub.choices[name].format_help().split())
        assert "direct: register frame 0 to each frame" in text, name


def test_no_progress_is_accepted_by_every_command(data, results, capsys, tmp_path):
    # plot, measure and info stopped with "unrecognized arguments: --no-progress" (exit 2) in a script passing it
    # to every command
    argv = {"info": ["info", data / "good.npz"],
            "plot": ["plot", results[0], "-o", tmp_path / "p.png", "--dpi", "30"],
            "measure": ["measure", results[0], "--inclusion", "6", "4", "2"]}
    for name, args in argv.items():
        rc, out, err = _run([*args, "--no-progress"], capsys)
        assert rc == 0, (name, rc, err)


def test_an_empty_background_or_inclusion_says_which(results, capsys):
    # "ROI mask must leave finite samples both inside and outside": neither which region was empty nor what to do
    rc, out, err = _run(["measure", results[0], "--inclusion", "6", "4", "40"], capsys)
    assert rc == 2 and "the background holds no finite sample" in err and "a smaller radius" in err, err


def test_a_frame_check_names_the_file_it_judged(data, capsys, tmp_path):
    # "the frames look transposed: ..." named no file, where the checks on the file as read (centimetres, the
    # raw --shape, the sample type) begin with it
    for argv, lead in ((["register", data / "transposed.npz"], f"{data / 'transposed.npz'}: the frames look"),
                       (["track", data / "transposed.npz", "--no-progress"], f"{data / 'transposed.npz'}: the frames")):
        rc, out, err = _run([*argv, "-o", tmp_path / "x.npz" if argv[0] == "register" else tmp_path / "t"], capsys)
        assert rc == 2 and err.startswith(f"femreg {argv[0]}: error: {lead}"), err


def test_plot_reference_takes_the_results_spacing(data, results, capsys, tmp_path):
    # a raw / .npy reference needed --spacing again (exit 2, "spacing unknown") though the B-mode is drawn on the
    # result's grid; a --spacing other than the result's was taken silently (exit 0)
    from femreg.io import read_frames

    fr = read_frames(data / "good.npz")
    np.save(tmp_path / "ref.npy", fr.frames[0])
    rc, out, err = _run(["plot", results[0], "--reference", tmp_path / "ref.npy", "-o", tmp_path / "p.png",
                         "--dpi", "30"], capsys)
    assert rc == 0 and (tmp_path / "p.png").is_file(), err
    dx, dy = (float(v) for v in fr.spacing)
    rc, out, err = _run(["plot", results[0], "--reference", tmp_path / "ref.npy", "--spacing", 2 * dx, 2 * dy,
                         "-o", tmp_path / "q.png", "--dpi", "30"], capsys)
    assert rc == 2 and "differs from the result's" in err and not (tmp_path / "q.png").exists(), err
    # invert --images reads its frames the same way (the refusal comes before any work)
    rc, out, err = _run(["invert", results[0], "--images", tmp_path / "ref.npy", tmp_path / "ref.npy", "--spacing",
                         2 * dx, 2 * dy, "-o", tmp_path / "mu.npz", "--no-progress"], capsys)
    assert rc == 2 and "differs from the result's" in err and not (tmp_path / "mu.npz").exists(), err


def test_transposed_frames_fixed_by_the_transpose_flag(data, capsys, tmp_path):
    # frames stored lines first: the refusal names --transpose, and the flag reads them right in every command
    # that reads frames (the file's own spacing, stored in its axes' order, goes with them)
    t = data / "transposed.npz"
    rc, out, err = _run(["register", t, "-o", tmp_path / "r.npz"], capsys)
    assert rc == 2 and "--transpose" in err, err
    rc, out, err = _run(["register", t, "-o", tmp_path / "r.npz", "--transpose"], capsys)
    assert rc == 0 and (tmp_path / "r.npz").is_file(), err
    import femreg

    good = femreg.load_result(tmp_path / "r.npz")
    assert good.shape == tuple(np.load(data / "good.npz")["rf"].shape[1:]), good.shape
    rc, out, err = _run(["info", t, "--transpose"], capsys)
    assert rc == 0 and "transposed as read" in out, out + err
    rc, out, err = _run(["track", t, "-o", tmp_path / "run", "--transpose", "--no-progress"], capsys)
    assert rc == 0 and (tmp_path / "run" / "frame_001.npz").is_file(), out + err
    # a result's pictures and its one-step inversion from frames stored lines first
    rc, out, err = _run(["plot", tmp_path / "r.npz", "-o", tmp_path / "r.png", "--reference", t], capsys)
    assert rc == 2 and "--transpose" in err, err
    rc, out, err = _run(["plot", tmp_path / "r.npz", "-o", tmp_path / "r.png", "--reference", t, "--transpose"],
                        capsys)
    assert rc == 0 and (tmp_path / "r.png").is_file(), err
    rc, out, err = _run(["invert", tmp_path / "r.npz", "-o", tmp_path / "mu.npz", "--images", t, "--no-progress"],
                        capsys)
    assert rc == 2 and "--transpose" in err, err
    # without a spacing (npy): info already says what the frames need besides it
    np.save(tmp_path / "t.npy", np.load(t)["rf"])
    rc, out, err = _run(["info", tmp_path / "t.npy"], capsys)
    assert rc == 1 and "no spacing found" in out and "pass --transpose" in out, out
    rc, out, err = _run(["info", tmp_path / "t.npy", "--transpose"], capsys)
    assert rc == 1 and "--transpose" not in out.split("needs", 1)[1], out
    # one spacing given, one from the file, would mix the two orders
    rc, out, err = _run(["info", t, "--transpose", "--spacing", "auto", "0.2"], capsys)
    assert rc == 2 and "both spacings" in err, err


def test_batch_stores_and_compares_transpose(data, capsys, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    (src / "t.npz").write_bytes((data / "transposed.npz").read_bytes())
    base = ["batch", "--workers", "0", "--no-progress", src, "-o", tmp_path / "b"]
    rc, out, err = _run(base + ["--transpose"], capsys)
    assert rc == 0, out + err
    manifest = json.loads(next((tmp_path / "b").glob("*.json")).read_text())
    assert [t["settings"]["transpose"] for t in manifest["tasks"].values()] == [True]
    rc, out, err = _run(base + ["--transpose", "--resume"], capsys)
    assert rc == 0 and "1 kept" in out, out + err
    rc, out, err = _run(base + ["--resume", "--no-orientation-check"], capsys)   # the flag dropped: changed
    assert rc == 2 and "settings or inputs changed" in err and "transpose)" in err, err


def test_failed_computation_reads_differently_from_bad_input(data, capsys, tmp_path):
    # exit 1 (computed, failed) says "failed:", exit 2 (bad input) "error:"
    rc, out, err = _run(["register", data / "unrelated.npz", "-o", tmp_path / "f.npz", "--maxiter", "3"], capsys)
    assert rc == 1 and err.startswith("femreg register: failed: ") and "error:" not in err, err
    rc, out, err = _run(["register", data / "missing.npz", "-o", tmp_path / "m.npz"], capsys)
    assert rc == 2 and err.startswith("femreg register: error: "), err
    from femreg.cli import build_parser

    sub = next(a for a in build_parser(["register"])._actions if hasattr(a, "choices") and a.choices)
    epilog = sub.choices["register"].epilog
    assert "'failed:'" in epilog and "'error:'" in epilog, epilog
