"""`femreg track`: checkpoints, --resume after an interruption, exit code 2 on bad input."""

import numpy as np
import pytest

from femreg.cli import main
from femreg.synthetic import speckle_image, warp_image

from _torn import tear_atomic_write

SPACING = (0.05, 0.2)


@pytest.fixture(scope="module")
def npy_sequence(tmp_path_factory):
    rng = np.random.default_rng(5)
    ref = speckle_image((200, 50), SPACING, rng)
    frames = [ref] + [warp_image(ref, SPACING, (0, 0), lambda p, s=s: np.column_stack(
        [-s * 0.004 * p[:, 0], s * 0.002 * (p[:, 1] - 5.0)])) for s in (1, 2, 3)]
    path = tmp_path_factory.mktemp("seq") / "frames.npy"
    np.save(path, np.stack(frames).astype(np.float32))
    return path


ARGS = ["-r", "strain", "--alpha", "3", "--element-size", "1", "--margin", "1", "--spacing", "0.05", "0.2",
        "--no-progress"]


def test_resume_recomputes_only_missing_frames(npy_sequence, tmp_path, capsys, monkeypatch):

    full, part = tmp_path / "full", tmp_path / "part"
    assert main(["track", str(npy_sequence), "-o", str(full)] + ARGS) == 0
    # Interrupt the run while frame 3 is being written: the writer's own temporary file is left half written.
    torn = tear_atomic_write(monkeypatch, lambda p: p.name == "frame_003.npz")
    assert main(["track", str(npy_sequence), "-o", str(part)] + ARGS) == 130
    monkeypatch.undo()
    assert torn and torn[0].exists() and not (part / "frame_003.npz").exists(), torn
    mtimes = {p.name: p.stat().st_mtime_ns for p in part.glob("frame_00[12].npz")}
    capsys.readouterr()
    assert main(["track", str(npy_sequence), "-o", str(part), "--resume"] + ARGS) == 0
    out = capsys.readouterr().out
    assert "1 computed, 2 resumed" in out, out
    assert {p.name: p.stat().st_mtime_ns for p in part.glob("frame_00[12].npz")} == mtimes
    for k in (1, 2, 3):
        a = np.load(full / f"frame_{k:03d}.npz")
        b = np.load(part / f"frame_{k:03d}.npz")
        assert np.array_equal(a["u"], b["u"]), f"frame {k} differs after resume"


def test_existing_run_without_resume_is_refused(npy_sequence, tmp_path, capsys):
    assert main(["track", str(npy_sequence), "-o", str(tmp_path), "--frames", "0:2"] + ARGS) == 0
    capsys.readouterr()
    assert main(["track", str(npy_sequence), "-o", str(tmp_path), "--frames", "0:2"] + ARGS) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("femreg track: error:") and "--resume" in err and "\n" not in err


@pytest.mark.parametrize("extra, needle", [
    (["--alpha", "-1"], "alpha"),
    (["--element-size", "1", "2", "3"], "element-size"),
    (["--frames", "0"], "at least 2 frames"),
])
def test_bad_input_exit_2(npy_sequence, tmp_path, capsys, extra, needle):
    assert main(["track", str(npy_sequence), "-o", str(tmp_path / "o")] + ARGS + extra) == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err, err


def test_missing_file_exit_2(tmp_path, capsys):
    assert main(["track", str(tmp_path / "nope.npy"), "-o", str(tmp_path / "o")] + ARGS) == 2
    assert "nope.npy" in capsys.readouterr().err


def test_register_pair_from_one_multiframe_file(npy_sequence, tmp_path, capsys):
    out = tmp_path / "pair.npz"
    assert main(["register", str(npy_sequence), "--pair", "0", "2", "-o", str(out)] + ARGS[:-1]) == 0
    z = np.load(out)
    assert z["exx"].shape == (200, 50)
    # frame 2 is a -0.8 % axial compression of frame 0 (moving(x + u) = reference(x), u_x = -0.008 x)
    exx = z["exx"][np.isfinite(z["exx"])]
    assert abs(np.median(exx) + 0.008) < 0.001, f"median exx {np.median(exx):.5f}, expected -0.008"
    assert "note" not in capsys.readouterr().err          # the pair was named: nothing to say
    assert main(["register", str(npy_sequence), "--pair", "0", "9", "-o", str(out)] + ARGS[:-1]) == 2
    assert "frame 9" in capsys.readouterr().err
    # a loop of 4 frames without --pair: frames 0 -> 1, and the command says so
    assert main(["register", str(npy_sequence), "-o", str(out)] + ARGS[:-1]) == 0
    err = capsys.readouterr().err
    assert "holds 4 frames: registering frames 0 -> 1" in err and "--pair" in err, err


def test_hourglass_flag(npy_sequence, tmp_path, capsys):
    base = ["register", str(npy_sequence), "--pair", "0", "1", "--spacing", "0.05", "0.2", "--element-size", "1",
            "--margin", "1"]
    assert main(base + ["-r", "momentum-stress", "--hourglass", "5", "-o", str(tmp_path / "a.npz")]) == 0
    assert main(base + ["-r", "strain", "--hourglass", "5", "-o", str(tmp_path / "b.npz")]) == 2
    assert "--hourglass applies to the momentum" in capsys.readouterr().err


def test_unwritable_output_exit_2(npy_sequence, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    rc = main(["track", str(npy_sequence), "-o", str(blocker / "sub")] + ARGS)
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err and err.count("\n") == 1, err


def test_plot_of_a_tracked_frame_says_what_it_accumulates(npy_sequence, tmp_path):
    """A frame of an accumulated run is frame 0 -> k; its NCC is that of the last increment, and the picture's
    title says both (a direct run's frame is a plain pair 0 -> k)."""
    import matplotlib

    matplotlib.use("Agg")
    from femreg.plot import plot_result

    acc, direct = tmp_path / "acc", tmp_path / "direct"
    assert main(["track", str(npy_sequence), "-o", str(acc)] + ARGS) == 0
    assert main(["track", str(npy_sequence), "-o", str(direct), "--mode", "direct"] + ARGS) == 0
    # whitespace as one space: a title wider than the figure is wrapped onto lines
    title = " ".join(plot_result(str(acc / "frame_003.npz"))._suptitle.get_text().split())
    assert title.startswith("frame 0 -> 3 (accumulated)") and "(frame 2 -> 3, before -> after)" in title, title
    title = " ".join(plot_result(str(direct / "frame_003.npz"))._suptitle.get_text().split())
    assert title.startswith("frame 0 -> 3,") and "accumulated" not in title and "frame 2 -> 3" not in title, title
