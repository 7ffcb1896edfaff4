"""What a first use of the command line trips over: frame indices counted from 0 everywhere (a negative
one refused with the valid range), a flagged inversion's message printed once, track.json saying which shape is
the frames' and which the registered region's, progress bars with a total (invert's beta sweep, --alpha auto's
candidates) and the one-line notice of a cold numba cache.  Small simulated L7 pairs (forward.pairs); the in vivo
recording only where it is found."""
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from femreg.cli import main
from femreg.io import save_frames

from test_io import INVIVO

SEQ = INVIVO / "seq299"
RAW = ["--shape", "2000", "128", "--spacing", "0.02", "0.2"]
needs_invivo = pytest.mark.skipif(not (SEQ / "frame1.raw").is_file(), reason=f"in vivo data not found at {SEQ}")
ROOT = Path(__file__).resolve().parents[1]
#: zero rows below the echo: the echo detection cuts them off, so the registered region is shorter than the frames
DEAD_ROWS = 60


def _run(argv, capsys):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """``pair.npz`` (a 1 % compression, 2 frames), ``loop.npz`` (3 frames with DEAD_ROWS zero rows below the
    echo) and ``ok.npz``, the pair's registration."""
    from forward import fields as F
    from forward.pairs import make_pair

    d = tmp_path_factory.mktemp("newcomer")
    p = make_pair(F.compression(0.01), "L7", (12.0, 8.0), 30, seed=0)
    sp = tuple(p.spacing)
    save_frames(d / "pair.npz", np.stack([p.ref, p.mov]), sp)
    dead = np.zeros((DEAD_ROWS, p.ref.shape[1]))
    save_frames(d / "loop.npz", np.stack([np.vstack([f, dead]) for f in (p.ref, p.mov, p.mov)]), sp)
    assert main(["register", str(d / "pair.npz"), "-o", str(d / "ok.npz"), "--no-progress"]) == 0
    return d


# ---------------------------------------------------------------------------------------------- frame indices
def test_negative_frame_indices_are_refused_with_the_valid_range(data, tmp_path, capsys):
    d = data
    for argv in (["register", d / "pair.npz", "--pair", "0", "-1", "-o", tmp_path / "r.npz"],
                 ["track", d / "loop.npz", "--frames", "0:-1", "-o", tmp_path / "t"],
                 ["track", d / "loop.npz", "--frames=-2,0", "-o", tmp_path / "t2"],
                 ["elastogram", d / "loop.npz", "--frames=-3:", "-o", tmp_path / "e"],
                 ["plot", d / "ok.npz", "--reference", d / "pair.npz", "--frame", "-1", "-o", tmp_path / "p.png"],
                 ["invert", d / "ok.npz", "--images", d / "pair.npz", "--pair", "-1", "0", "-o", tmp_path / "m.npz"]):
        rc, out, err = _run(argv, capsys)
        n = 3 if argv[0] in ("track", "elastogram") else 2
        assert rc == 2 and f"counted from 0: 0 to {n - 1}" in err and "negative" in err, (argv, err)
        assert err.count("\n") == 1 and not list(tmp_path.rglob("*.np[zy]")) and not list(tmp_path.glob("*.png"))
    # the same indices counted from 0 are read
    rc, out, err = _run(["plot", d / "ok.npz", "--reference", d / "pair.npz", "--frame", "1",
                         "-o", tmp_path / "p.png"], capsys)
    assert rc == 0, err


def test_negative_index_of_a_selection():
    from femreg.options import frame_selection, negative_index

    assert [negative_index(frame_selection(t)) for t in ("3", "0:4", "4:0:-1", "1,3", "::-1")] == [None] * 5
    assert [negative_index(frame_selection(t)) for t in ("-1", "0:-1", "-3:", "2,-1")] == [-1, -1, -3, -1]


# ---------------------------------------------------------------------------------------------- invert
def test_a_flagged_inversion_says_its_message_once(data, tmp_path, capsys):
    import femreg.inversion as inv

    # plane stress on a plane-strain compression (strain ratio 0.98 against 0.5): flagged, exit 1
    rc, out, err = _run(["invert", data / "ok.npz", "-o", tmp_path / "mu.npz", "--model", "plane-stress",
                         "--no-progress"], capsys)
    message = inv.load_inversion(tmp_path / "mu.npz").message
    assert rc == 1 and "contradicts the plane-stress model" in message, (rc, message)
    assert (out + err).count(message) == 1 and "FLAGGED" in err and "message=" not in out, (out, err)
    assert out.startswith("inversion: flagged, model plane-stress"), out
    # a successful one keeps its message in the summary line
    rc, out, err = _run(["invert", data / "ok.npz", "-o", tmp_path / "ok.npz", "--no-progress"], capsys)
    ok = inv.load_inversion(tmp_path / "ok.npz").message
    assert rc == 0 and ok and out.splitlines()[0].endswith(f"; {ok}"), out


def test_invert_progress_bar_counts_beta_values(data, tmp_path, capsys):
    rc, out, err = _run(["invert", data / "ok.npz", "-o", tmp_path / "mu.npz", "--beta", "0.01"], capsys)
    last = err.replace("\r", "\n").strip().splitlines()
    bar = [s for s in last if s.startswith("invert:")]
    # one given beta: a bar of 1 beta value, not a bare count of optimiser iterations ("800it")
    assert rc == 0 and bar and "1/1" in bar[-1] and "beta" in bar[-1], err
    assert not re.search(r"\d+it \[", err), err


# ---------------------------------------------------------------------------------------------- track.json
def test_track_json_says_frame_shape_and_registered_region(data, tmp_path, capsys):
    out_dir = tmp_path / "run"
    rc, out, err = _run(["track", data / "loop.npz", "-o", out_dir, "--no-progress"], capsys)
    assert rc == 0, err
    rec = json.loads((out_dir / "track.json").read_text())
    with np.load(data / "loop.npz") as z:
        frame_shape = list(z["rf"].shape[1:])
    reg = rec["registered_region"]
    assert rec["frame_shape"] == frame_shape and rec["frame_origin"] == [0.0, 0.0]
    # the dead rows are cut off: the region (and the earlier "shape", kept for its readers) is shorter
    assert reg["rows"][0] == 0 and frame_shape[0] - DEAD_ROWS - 5 <= reg["rows"][1] < frame_shape[0], reg
    assert rec["shape"] == reg["shape"] == [reg["rows"][1] - reg["rows"][0], reg["cols"][1] - reg["cols"][0]]
    with np.load(out_dir / "frame_002.npz") as z:
        assert list(z["exx"].shape) == frame_shape
    # a folder written before these entries (no frame_shape ...) still resumes
    for key in ("frame_shape", "frame_origin", "registered_region", "shape_note"):
        rec.pop(key)
    (out_dir / "track.json").write_text(json.dumps(rec))
    rc, out, err = _run(["track", data / "loop.npz", "-o", out_dir, "--no-progress", "--resume"], capsys)
    assert rc == 0 and "registered_region" in (out_dir / "track.json").read_text(), err


@needs_invivo
def test_track_json_of_the_invivo_loop(tmp_path, capsys):
    rc, out, err = _run(["track", SEQ, *RAW, "--frames", "0:2", "-o", tmp_path / "run", "--no-progress"], capsys)
    assert rc in (0, 1), err
    rec = json.loads((tmp_path / "run" / "track.json").read_text())
    # measured: depth below 38.5 mm holds zero samples; rows 0-1923 of 2000 registered
    assert rec["frame_shape"] == [2000, 128] and rec["shape"] == [1923, 128], rec
    assert rec["registered_region"]["rows"] == [0, 1923]


# ---------------------------------------------------------------------------------------------- progress
def test_alpha_auto_progress_bar_on_the_command_line_only(data, tmp_path, capsys):
    import femreg

    rc, out, err = _run(["register", data / "pair.npz", "--alpha", "auto", "-o", tmp_path / "a.npz"], capsys)
    # 7 candidates: a registration and an influence trace each
    assert rc == 0 and "alpha auto" in err and "14/14" in err, err
    rc, out, err = _run(["register", data / "pair.npz", "--alpha", "auto", "-o", tmp_path / "b.npz",
                         "--no-progress"], capsys)
    assert rc == 0 and "alpha auto" not in err, err
    with np.load(data / "pair.npz") as z:
        femreg.register(z["rf"][0], z["rf"][1], spacing=tuple(z["spacing"]), alpha="auto")
    assert "alpha auto" not in capsys.readouterr().err        # a library call stays silent


def test_cold_kernel_cache_is_detected(tmp_path):
    """A fresh NUMBA_CACHE_DIR is cold; compiling one kernel there makes it warm; the notice is said once."""
    code = ("import numpy as np\n"
            "from femreg import _kernels as k\n"
            "said = []\n"
            "k.notify_cold_cache(said.append)\n"
            "cold = k.cache_is_cold()\n"
            "k.use_compiled(); k.use_compiled()\n"
            "k.modulus(np.ones((2, 2)), np.ones((2, 2)))\n"
            "print(cold, said == [k.COLD_CACHE_MESSAGE], k.cache_is_cold())\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), PYTHONPATH=str(ROOT))
    env.pop("FEMREG_NUMBA", None)
    pytest.importorskip("numba")
    got = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert got.stdout.split() == ["True", "True", "False"], (got.stdout, got.stderr)


def test_cold_cache_notice_on_a_terminal_only(data, tmp_path, capsys, monkeypatch):
    import femreg.cli as cli
    from femreg import _kernels

    monkeypatch.setattr(_kernels, "cache_is_cold", lambda: True)
    monkeypatch.setattr(cli, "_stderr_is_terminal", lambda: True)
    rc, out, err = _run(["register", data / "pair.npz", "-o", tmp_path / "a.npz", "--no-progress"], capsys)
    line = f"femreg register: {_kernels.COLD_CACHE_MESSAGE}"
    assert rc == 0 and err.count(line) == (1 if _kernels.use_compiled() else 0), err
    monkeypatch.setattr(cli, "_stderr_is_terminal", lambda: False)
    rc, out, err = _run(["register", data / "pair.npz", "-o", tmp_path / "b.npz", "--no-progress"], capsys)
    assert rc == 0 and _kernels.COLD_CACHE_MESSAGE not in err, err


# ---------------------------------------------------------------------------------------------- bad flags
def test_bad_numbers_are_refused_before_any_work_in_the_flags_units(data, tmp_path, capsys):
    d = data
    cases = [
        # a ZeroDivisionError traceback (exit 1) after the whole loop was registered
        (["elastogram", d / "loop.npz", "--fps", "0", "-o", tmp_path / "e"], "--fps must be a number > 0"),
        # said in fractions, "got (0.02, 0.01)", of a flag given in percent
        (["elastogram", d / "loop.npz", "--band", "2", "1", "-o", tmp_path / "e"], "0 < LO < HI < 20 (percent"),
        # "got (np.float64(0.0), np.float64(0.0))"
        (["register", d / "pair.npz", "--element-size", "0", "-o", tmp_path / "r.npz"], "> 0 mm, got 0"),
        (["track", d / "loop.npz", "--margin", "-1", "-o", tmp_path / "t"], ">= 0 (mm), got -1"),
        # an IndexError traceback (exit 1): a 2 x 2 mesh has no element off its boundary
        (["invert", d / "ok.npz", "--region", "4", "5", "3", "4", "-o", tmp_path / "m.npz", "--no-progress"],
         "no element off its boundary"),
        # refused only after the whole inversion had run (10.9 s on seq299), without the mesh's span
        (["invert", d / "ok.npz", "--reference", "100", "200", "1", "2", "10", "-o", tmp_path / "m.npz",
          "--no-progress"], "holds no element centre; the mesh spans x"),
    ]
    for argv, says in cases:
        rc, out, err = _run(argv, capsys)
        assert rc == 2 and says in err and "np.float64" not in err, (argv[0], rc, err)
        assert err.count("\n") == 1 and "Traceback" not in err, err
    assert not any(tmp_path.iterdir())


def test_register_prints_a_readable_result_line(data, tmp_path, capsys):
    # before: the library's repr, "RegistrationResult(regularizer='momentum-stress', alpha=0.133, success=True, ..."
    rc, out, err = _run(["register", data / "pair.npz", "-o", tmp_path / "r.npz", "--no-progress"], capsys)
    line = out.splitlines()[0]
    assert rc == 0 and line.startswith("pair: ncc ") and " nodes, regularizer momentum-stress, alpha " in line, out
    assert "RegistrationResult(" not in out and "=" not in line.split(";")[0], out
