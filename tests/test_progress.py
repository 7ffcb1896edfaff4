"""Progress on a stderr that is not a terminal (a log file, a pipe, a test's capture): plain lines, no bars."""
import numpy as np

from femreg import progress


def test_lines_not_bars_off_a_terminal(capsys):
    b = progress.bar(total=100, desc="track (accumulate)", unit="frame")
    assert isinstance(b, progress.LineProgress)          # capsys' stderr is no terminal
    for _ in range(100):
        b.update(1)
        b.set_postfix_str("ncc 0.99")
    b.close()
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert "\r" not in err and "\x1b" not in err, repr(err[:200])
    # a line per tenth of the total (10), none repeated at close: 100 updates give 10 lines, not 100
    assert len(lines) == 10, lines
    assert lines[0].startswith("track (accumulate): 10/100 frames (10 %)") and lines[-1].endswith("ncc 0.99")


def test_a_slow_step_still_says_something(capsys, monkeypatch):
    monkeypatch.setattr(progress, "LINE_SECONDS", 0.0)   # every call is "long after the last line"
    b = progress.LineProgress(total=1000, desc="invert", unit="beta")
    b.set_postfix_str("beta 0.1, iteration 120 of at most 400")
    b.total += 1                                         # extended, as the inversion's sweep does
    b.update(1)
    b.close()
    lines = capsys.readouterr().err.splitlines()
    progress.LineProgress(total=0, desc="register", unit="pair").close()      # nothing to do: no line
    assert capsys.readouterr().err == ""
    assert lines[0] == "invert: 0/1000 betas (0 %), 0.0 s, beta 0.1, iteration 120 of at most 400", lines
    assert lines[1].startswith("invert: 1/1001 beta (0 %)") and len(lines) == 2, lines


def test_iterate_yields_everything_with_lines(capsys):
    assert list(progress.iterate(range(3), desc="data sets", unit="set")) == [0, 1, 2]
    lines = capsys.readouterr().err.splitlines()
    assert lines[-1].startswith("data sets: 3/3 sets (100 %)") and len(lines) == 3, lines


def test_track_on_a_log_writes_lines(tmp_path, capsys):
    from femreg.cli import main
    from femreg.synthetic import speckle_pair

    def shift(p):
        return np.column_stack([0.01 * p[:, 0], np.zeros(len(p))])

    ref, mov = speckle_pair(shift, (300, 40), (0.025, 0.2), seed=3)
    np.save(tmp_path / "f.npy", np.stack([ref, mov, mov]).astype(np.float32))
    rc = main(["track", str(tmp_path / "f.npy"), "--spacing", "0.025", "0.2", "-o", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert rc in (0, 1) and "\r" not in err, repr(err)
    # the per-frame lines are the progress: their count and time, no progress lines repeating them
    assert "frame   1: ncc" in err and "(1/2, " in err and "(2/2, " in err, err
    assert "track (accumulate)" not in err and err.count("frame   2:") == 1, err
    rc = main(["track", str(tmp_path / "f.npy"), "--spacing", "0.025", "0.2", "-o", str(tmp_path / "run2"),
               "--no-progress"])
    assert "frames (" not in capsys.readouterr().err                     # --no-progress: silent
